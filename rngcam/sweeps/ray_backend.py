"""Ray tasks for sweeps and batches: a local Ray by default, an existing cluster by address.

Each item is one task with one CPU (and `gpus_per_task` GPUs). A task whose worker dies (killed,
out of memory, node lost) is retried by Ray up to `max_retries` times; trials resume from their
own checkpoints, so a retry continues rather than restarts. Shared data (the Problem) is put in
the object store once. On a cluster, workers need rngcam installed, and batch outputs go to
paths that every node must reach (a shared file system).

A local Ray (`LocalRay`) stays on loopback: its node address is 127.0.0.1, usage statistics are
off, and the cloud-provider probe that Ray's head runs at start (HTTP to the metadata address
169.254.169.254 and a DNS query, with statistics off too) is sent to a loopback port that
refuses it. Its session files live in a private folder removed at stop, and its token is in
the environment of its own processes, so nothing is written to ~/.ray.
"""

from __future__ import annotations

import logging
import os
import secrets
import shutil
import socket
import tempfile

from rngcam.errors import RngcamError
from rngcam.sweeps.tasks import OnResult, TaskFn, failed

LOOPBACK = "127.0.0.1"
_NO_PROXY = "127.0.0.1,localhost,::1"
_QUIET = {"log_to_driver": False, "logging_level": logging.ERROR}  # our own lines say what runs
_TOKEN: list[str] = []  # one token per process: the driver's Ray caches the first it reads


def _local_env(refusing_port: int) -> dict[str, str]:
    """Environment for a local Ray and every process it starts (workers inherit it)."""
    if not _TOKEN:
        _TOKEN.append(secrets.token_hex(32))
    proxy = f"http://{LOOPBACK}:{refusing_port}"
    return {
        "RAY_USAGE_STATS_ENABLED": "0",
        # Ray's switch for 'this node may join a cluster': off, a node's address is loopback and
        # no process looks for a public one (a UDP connect to 8.8.8.8).
        "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0",
        "RAY_AUTH_TOKEN": _TOKEN[0],
        # The head's usage module asks cloud metadata servers which cloud this is, whatever the
        # statistics setting; through a proxy that refuses, those requests stay on loopback.
        **{name: proxy for name in ("http_proxy", "HTTP_PROXY", "https_proxy", "HTTPS_PROXY")},
        "no_proxy": _NO_PROXY, "NO_PROXY": _NO_PROXY,
        # A local Ray starts its workers at nice 15: on a busy workstation the trials would starve
        # behind any other work.
        "RAY_worker_niceness": "0",
    }


class LocalRay:
    """A Ray started in this process on loopback only, with its files in a private folder; stop() ends it."""

    def __init__(self, num_cpus: int | None = None):
        self._saved: dict[str, str | None] = {}
        self._refuser = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._refuser.bind((LOOPBACK, 0))  # bound, never listening: a connection to it is refused
        self.folder = tempfile.mkdtemp(prefix="rngcam-ray-")  # mode 0700
        self._set_env(_local_env(self._refuser.getsockname()[1]))
        # Unset, a local Ray turns token authentication on (and reloads its own settings to see it).
        self._saved.setdefault("RAY_AUTH_MODE", os.environ.pop("RAY_AUTH_MODE", None))
        import ray  # optional: cluster extra

        constants = ray._private.ray_constants
        # Read once at `import ray`: set here too where this process imported Ray before.
        self._cluster_switch = getattr(constants, "ENABLE_RAY_CLUSTER", None)
        if self._cluster_switch is not None:
            constants.ENABLE_RAY_CLUSTER = False
        self._ray = ray
        try:
            # Ray makes its temporary folder writable by all: a subfolder of our own 0700 one.
            ray.init(num_cpus=num_cpus, include_dashboard=False, _node_ip_address="127.0.0.1",  # LOOPBACK
                     _temp_dir=os.path.join(self.folder, "ray"), **_QUIET)
            address = ray.util.get_node_ip_address()
        except Exception as exc:  # noqa: BLE001 - start-up failures vary by version
            self.stop()
            raise RngcamError(f"cannot start a local Ray: {exc}".splitlines()[0]) from None
        if address != LOOPBACK:
            self.stop()
            raise RngcamError(f"a local Ray would listen on {address}, not on loopback ({LOOPBACK}): not started")

    def _set_env(self, env: dict[str, str]) -> None:
        for name, value in env.items():
            self._saved.setdefault(name, os.environ.get(name))
            os.environ[name] = value

    def stop(self) -> None:
        """Stop Ray, remove its private folder and give this process back its environment."""
        if self._ray is not None and self._ray.is_initialized():
            self._ray.shutdown()
        if self._cluster_switch is not None:
            self._ray._private.ray_constants.ENABLE_RAY_CLUSTER = self._cluster_switch
        self._ray, self._cluster_switch = None, None
        for name, value in self._saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value
        self._saved = {}
        self._refuser.close()
        shutil.rmtree(self.folder, ignore_errors=True)

    _ray = None
    _cluster_switch = None


class RayBackend:
    """Runs tasks on Ray; starts a local Ray on loopback (and stops it at close) unless one is running."""

    threads_per_task = 1  # one CPU per task

    def __init__(self, address: str | None = None, num_cpus: int | None = None, max_retries: int = 3,
                 gpus_per_task: float = 0.0):
        import ray  # optional: cluster extra

        self._ray, self.max_retries, self.gpus_per_task = ray, int(max_retries), float(gpus_per_task)
        self._local: LocalRay | None = None
        if not ray.is_initialized():
            if address:
                os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
                try:
                    ray.init(address=address, **_QUIET)
                except Exception as exc:  # noqa: BLE001 - connection failures vary by version
                    raise RngcamError(f"cannot join the Ray cluster at {address}: {exc}".splitlines()[0]) from None
                self._joined = True
            else:
                self._local = LocalRay(num_cpus)
        cpus = int(ray.cluster_resources().get("CPU", 0))
        self.name = f"Ray ({'cluster at ' + address if address else 'local'}, {cpus} CPUs)"

    _joined = False

    def map(self, fn: TaskFn, items: list, shared: object = None, on_result: OnResult | None = None) -> list[dict]:
        ray = self._ray
        remote = ray.remote(num_cpus=1, num_gpus=self.gpus_per_task, max_retries=self.max_retries)(fn)
        shared_ref = ray.put(shared)
        pending = {remote.remote(item, shared_ref): i for i, item in enumerate(items)}
        results: list[dict | None] = [None] * len(items)
        while pending:
            # A timeout keeps the wait interruptible: Ctrl-C stops the run (close() then stops Ray).
            ready, _ = ray.wait(list(pending), num_returns=1, timeout=1.0)
            for ref in ready:
                i = pending.pop(ref)
                try:
                    results[i] = ray.get(ref)
                except Exception as exc:  # noqa: BLE001 - worker lost after every retry, or the task raised
                    results[i] = failed(f"{type(exc).__name__}: {exc}".splitlines()[0])
                if on_result is not None:
                    on_result(i, results[i])
        return results  # type: ignore[return-value]

    def close(self) -> None:
        if self._local is not None:
            self._local.stop()
            self._local = None
        elif self._joined:
            self._ray.shutdown()
            self._joined = False
