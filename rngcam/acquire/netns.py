"""A private network namespace for simulated GigE cameras, so nothing leaves loopback.

Aravis's fake GigE camera binds GVCP port 3956 on one address, so two fake cameras need two
loopback addresses; and Aravis discovery broadcasts on every interface. A process that serves
fake cameras therefore runs in a network namespace of its own (`unshare --net`, with
`--map-root-user` when not root), where the only interface is loopback: `run_private` re-runs a
command there, and inside it `bring_up_loopback(addresses)` sets lo up with the extra
addresses (127.0.0.2 ...), with the kernel's ioctls (no `ip` binary needed).
"""

from __future__ import annotations

import fcntl
import os
import shutil
import socket
import struct
import subprocess

from rngcam.errors import HardwareError

ENV = "RNGCAM_PRIVATE_NETNS"  # set in the namespace's processes
_SIOCGIFFLAGS, _SIOCSIFFLAGS, _SIOCSIFADDR = 0x8913, 0x8914, 0x8916
_IFF_UP = 0x1


def inside() -> bool:
    """True in a process that run_private started."""
    return os.environ.get(ENV) == "1"


def unshare_prefix() -> list[str]:
    """The command prefix that runs a command in a new network namespace; HardwareError when
    this machine cannot (no unshare, or user namespaces off for a non-root user)."""
    exe = shutil.which("unshare")
    if exe is None:
        raise HardwareError("simulated GigE cameras need a private network namespace, and `unshare` "
                            "(util-linux) is not installed")
    prefix = [exe, "--net"] + ([] if os.geteuid() == 0 else ["--map-root-user"])
    with subprocess.Popen([*prefix, "true"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True) as probe:
        _, err = probe.communicate()
    if probe.returncode != 0:
        why = err.strip().splitlines()[-1] if err.strip() else f"exit {probe.returncode}"
        raise HardwareError(f"cannot create a private network namespace for simulated GigE cameras ({why}); "
                            "run as root or enable unprivileged user namespaces")
    return prefix


def run_private(argv: list[str], **kwargs) -> subprocess.CompletedProcess:
    """Run argv in a new network namespace (loopback only); its environment marks it inside()."""
    env = dict(kwargs.pop("env", None) or os.environ)
    env[ENV] = "1"
    return subprocess.run([*unshare_prefix(), *argv], env=env, **kwargs)


_added: list[str] = []  # loopback addresses this process added (lo:1, lo:2 ...)


def bring_up_loopback(addresses: list[str]) -> None:
    """lo up, plus each extra 127.x address as lo:1, lo:2 ... (only inside a private namespace)."""
    if not inside():
        raise HardwareError("refusing to change the network outside a private namespace")
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        flags = struct.unpack("16sH", fcntl.ioctl(s, _SIOCGIFFLAGS, struct.pack("16sH14s", b"lo", 0, b""))[:18])[1]
        fcntl.ioctl(s, _SIOCSIFFLAGS, struct.pack("16sH14s", b"lo", flags | _IFF_UP, b""))
        for address in addresses:
            if address == "127.0.0.1" or address in _added:
                continue
            if not address.startswith("127."):
                raise HardwareError(f"simulated cameras live on loopback: {address} is not a 127.x address")
            sin = struct.pack("HH4s8s", socket.AF_INET, 0, socket.inet_aton(address), b"")
            fcntl.ioctl(s, _SIOCSIFADDR, struct.pack("16s16s", f"lo:{len(_added) + 1}".encode(), sin))
            _added.append(address)
    except OSError as exc:
        raise HardwareError(f"cannot set up loopback addresses {addresses} in the private namespace ({exc})") from None
    finally:
        s.close()
