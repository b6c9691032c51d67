"""Ray's part of the tests runs in a network namespace of its own, where the only interface is
loopback (rngcam.acquire.netns, as the Aravis tests): whatever Ray tries, nothing leaves the
machine. `call(module, function, **kwargs)` runs a module-level function of a test module there
and returns what it returned (JSON); with `trace=PATH`, under `strace -f -e trace=connect,bind`."""

from __future__ import annotations

import json
import os
import re
import shutil
import sys
import textwrap
from pathlib import Path

from rngcam.acquire import netns
from rngcam.errors import HardwareError

REPO = Path(__file__).resolve().parents[1]
TESTS = Path(__file__).resolve().parent


def why_not() -> str | None:
    """Why Ray's tests cannot run here (Ray missing, no private namespace), or None."""
    try:
        import importlib.util

        if importlib.util.find_spec("ray") is None:
            return "Ray is not installed (pip install 'rngcam[cluster]')"
        netns.unshare_prefix()
    except HardwareError as exc:
        return f"Ray runs only in a private network namespace in tests, and {exc}"
    return None


def env(**extra: str) -> dict:
    path = os.pathsep.join([str(TESTS), str(REPO), os.environ.get("PYTHONPATH", "")])
    return {**os.environ, "PYTHONPATH": path, **extra}


def call(module: str, function: str, timeout: float = 240, trace: Path | None = None,
         extra_env: dict | None = None, **kwargs) -> dict:
    """module.function(**kwargs) in a private network namespace with lo up; its JSON result."""
    code = f"""
        import importlib, json, sys
        from rngcam.acquire import netns
        netns.bring_up_loopback(["127.0.0.1"])
        result = getattr(importlib.import_module({module!r}), {function!r})(**json.loads(sys.argv[1]))
        print(json.dumps(result))
    """
    argv = [sys.executable, "-c", textwrap.dedent(code), json.dumps(kwargs)]
    if trace is not None:
        argv = [shutil.which("strace"), "-f", "-qq", "--seccomp-bpf", "-e", "trace=connect,bind", "-o", str(trace), *argv]
    done = netns.run_private(argv, capture_output=True, text=True, timeout=timeout, env=env(**(extra_env or {})))
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


_CALL = re.compile(r"^\d+\s+(connect|bind)\(")
_ADDRESS = re.compile(r"^\d+\s+(connect|bind)\(\d+, \{sa_family=(AF_\w+)(.*?)\}, \d+")
_IPV4 = re.compile(r'sin_addr=inet_addr\("([\d.]+)"\)')
_IPV6 = re.compile(r'inet_pton\(AF_INET6, "([^"]+)"')


def addresses(trace: Path) -> list[tuple[str, str, str]]:
    """(call, family, address) of every connect and bind in an strace log: address '' where it has
    no IP (AF_UNIX ...), family '?' and the line itself where the line does not parse."""
    found = []
    for line in trace.read_text().splitlines():
        if not _CALL.match(line):
            continue
        m = _ADDRESS.match(line)
        if m is None:
            found.append((_CALL.match(line).group(1), "?", line))
            continue
        call_name, family, rest = m.groups()
        ip = _IPV4.search(rest) or _IPV6.search(rest)
        found.append((call_name, family, ip.group(1) if ip else ""))
    return found


def beyond_loopback(found: list[tuple[str, str, str]]) -> list[tuple[str, str, str]]:
    """Those that are not AF_UNIX/AF_NETLINK, 127.0.0.0/8, ::1 or ::ffff:127.x (AF_UNSPEC: a
    connect that dissolves a UDP socket's association, no destination)."""
    import ipaddress

    def local(family: str, address: str) -> bool:
        if family in ("AF_UNIX", "AF_NETLINK", "AF_UNSPEC"):
            return True
        if family not in ("AF_INET", "AF_INET6") or not address:
            return False
        ip = ipaddress.ip_address(address)
        mapped = getattr(ip, "ipv4_mapped", None)
        return (mapped or ip).is_loopback

    return [f for f in found if not local(f[1], f[2])]
