"""A local Ray stays on loopback: a tiny sweep and batch on Ray, traced with strace, connect and
bind to loopback or Unix sockets only (no cloud metadata probe, no DNS query, no public address
looked up, nothing listening on every interface); its token is in no file, its session files in
a private folder removed at stop. All of it inside a private network namespace (ray_private)."""

from __future__ import annotations

import os
import shutil
import stat
from pathlib import Path

import pytest
import ray_private

WHY_NOT = ray_private.why_not()
pytestmark = pytest.mark.skipif(WHY_NOT is not None, reason=str(WHY_NOT))
needs_strace = pytest.mark.skipif(shutil.which("strace") is None,
                                  reason="strace is not installed (apt-get install strace): cannot trace Ray")


def tiny_sweep_and_batch(folder: str) -> dict:
    """Runs in the namespace: one local Ray, a two-trial sweep and a one-bundle batch on it."""
    from rngcam.evaluate.synthetic import CaptureSpec, make_bundle
    from rngcam.recon.runner import ReconSettings
    from rngcam.sweeps.batch import recon_batch
    from rngcam.sweeps.ray_backend import LocalRay, RayBackend
    from rngcam.sweeps.sweep import SweepSettings, sweep

    work = Path(folder)
    bundle = make_bundle(CaptureSpec(height=12, width=12, seed=0), work / "a.h5")
    local = LocalRay(num_cpus=2)
    try:
        private = {"mode": stat.S_IMODE(os.stat(local.folder).st_mode), "owner": os.stat(local.folder).st_uid}
        settings = SweepSettings(method="tv3d", grid={"beta": [1.0, 10.0]}, max_iters=3, holdout=0.2, folds=1,
                                 rungs=1, refit=False)
        swept = sweep(bundle, work / "sweep", settings, backend_factory=RayBackend, echo=lambda s: None)
        batch = recon_batch([bundle], work / "batch", ReconSettings(method="tv3d", time_budget_s=None, max_iters=2,
                                                                   progress=False),
                            backend_factory=RayBackend, echo=lambda s: None)
    finally:
        local.stop()
    return {"backends": [swept.backend, batch.backend], "private": private, "folder_left": os.path.exists(local.folder),
            "statuses": [r["status"] for r in swept.rows + batch.rows],
            "token_env_after": "RAY_AUTH_TOKEN" in os.environ}


@needs_strace
def test_a_sweep_and_a_batch_on_ray_touch_loopback_only_and_leave_no_token_file(tmp_path):
    home = tmp_path / "home"  # Ray would write ~/.ray/auth_token here
    home.mkdir()
    real = Path.home()
    trace = tmp_path / "connect.trace"
    out = ray_private.call("test_ray_loopback", "tiny_sweep_and_batch", trace=trace, folder=str(tmp_path),
                           extra_env={"HOME": str(home), "XDG_CACHE_HOME": os.environ.get("XDG_CACHE_HOME",
                                      str(real / ".cache")), "XDG_CONFIG_HOME": str(real / ".config")})
    assert out["statuses"] == ["ok"] * 3 and all(b.startswith("Ray (local") for b in out["backends"])
    found = ray_private.addresses(trace)
    connects = [f for f in found if f[0] == "connect"]
    # Ray's processes did talk (over loopback TCP and Unix sockets), and strace saw them.
    assert sum(f[2].endswith("127.0.0.1") for f in connects) >= 10 and any(f[1] == "AF_UNIX" for f in connects)
    assert ray_private.beyond_loopback(found) == []
    assert out["private"] == {"mode": 0o700, "owner": os.getuid()} and not out["folder_left"]
    assert list(home.iterdir()) == [] and not out["token_env_after"]


def cloud_probe() -> dict:
    """Runs in the namespace: Ray's cloud-provider probe in a local Ray's environment."""
    import socket

    from rngcam.sweeps import ray_backend

    refuser = socket.socket()
    refuser.bind((ray_backend.LOOPBACK, 0))
    os.environ.update(ray_backend._local_env(refuser.getsockname()[1]))
    from ray._common.usage.usage_lib import get_cloud_from_metadata_requests

    return {"cloud": get_cloud_from_metadata_requests()}


@needs_strace
def test_rays_cloud_metadata_probe_is_refused_on_loopback(tmp_path):
    trace = tmp_path / "probe.trace"
    out = ray_private.call("test_ray_loopback", "cloud_probe", trace=trace, timeout=60)
    assert out == {"cloud": "unknown"}
    found = ray_private.addresses(trace)
    assert any(f[0] == "connect" and f[2] == "127.0.0.1" for f in found)  # the probe went to the refusing port
    assert ray_private.beyond_loopback(found) == []
