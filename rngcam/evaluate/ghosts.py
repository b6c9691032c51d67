"""Key-frame ghosts: how much of a key frame's content an in-between frame still shows where the
truth has moved away from it.

For an intermediate frame t with truth T, estimate E and a bracketing key frame's content A (the
truth at that key frame's time; the key frames before and after t are both used), per pixel p
(colour channels as a vector):

- the changed region M: |A(p) - T(p)| > `threshold` x the truth video's 99th-percentile
  intensity (so a dim scene is judged on its own scale);
- the ghost fraction a(p) = clip(<E(p) - T(p), A(p) - T(p)> / |A(p) - T(p)|^2, 0, 1): the
  estimate's position on the segment from the truth (0) to the key frame's content (1); a
  half-transparent ghost of the key frame reads 0.5;
- a key frame's presence: the mean of a over its M, weighted by |A - T|^2 (where the key frame
  differs the most counts the most);
- the frame's score: the larger presence of its two key frames (the ghost of the key frame that
  lingers most).

The score is 0 for the truth and for an estimate that moved the content to where it is, 1 for an
estimate that holds a key frame wherever the truth left it (the key frame's backdrop where the
object now is counts too: the object is missing there). A cross-fade of a moving disc scores about
0.8 (the nearer key frame's copy at more than half strength, the disc missing where it now is); the
disc drawn where it is but 0.7 px off, about 0.1.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

THRESHOLD = 0.1  # the changed region: |key - truth| above this fraction of the truth's p99 intensity


def frame_ghost(truth: np.ndarray, estimate: np.ndarray, keys: Sequence[np.ndarray],
                floor: float) -> float | None:
    """The ghost score (0..1) of one frame (3, H, W) against key-frame contents (3, H, W) each:
    the largest key frame's presence; None when no key frame differs from the truth by more than
    `floor` anywhere."""
    presences = []
    t, e = np.asarray(truth, np.float64), np.asarray(estimate, np.float64)
    for key in keys:
        d = np.asarray(key, np.float64) - t  # (3, H, W)
        energy = (d * d).sum(0)
        changed = energy > floor * floor
        if not changed.any():
            continue
        a = np.clip(((e - t) * d).sum(0)[changed] / energy[changed], 0.0, 1.0)
        presences.append(float((a * energy[changed]).sum() / energy[changed].sum()))
    return max(presences) if presences else None


def bracketing_keys(frame: int, key_frames: Sequence[int]) -> list[int]:
    """The key frames just before and just after `frame` (one at either end)."""
    keys = sorted(int(k) for k in key_frames)
    before = [k for k in keys if k <= frame]
    after = [k for k in keys if k >= frame]
    return sorted({*before[-1:], *after[:1]})


def ghost_scores(truth: np.ndarray, estimate: np.ndarray, key_frames: Sequence[int],
                 frames: Sequence[int], threshold: float = THRESHOLD) -> np.ndarray:
    """Per-frame ghost scores (NaN where nothing moved) of `estimate` against `truth`, both
    (3, K, H, W), on `frames` (the intermediate frames), the key frames' content taken from the
    truth at grid frames `key_frames`."""
    truth, estimate = np.asarray(truth), np.asarray(estimate)
    if truth.shape != estimate.shape or truth.ndim != 4:
        raise ValueError(f"truth {truth.shape} and estimate {estimate.shape} must both be (3, K, H, W)")
    floor = threshold * max(float(np.percentile(truth, 99)), 1e-12)
    out = np.full(len(frames), np.nan)
    for i, k in enumerate(frames):
        keys = [truth[:, g] for g in bracketing_keys(k, key_frames)]
        score = frame_ghost(truth[:, k], estimate[:, k], keys, floor)
        out[i] = np.nan if score is None else score
    return out


def ghost_summary(scores: np.ndarray) -> dict:
    """Mean, 90th percentile and max of per-frame scores (NaN frames left out; all None if none)."""
    s = np.asarray(scores, float)
    s = s[np.isfinite(s)]
    if s.size == 0:
        return {"ghost_mean": None, "ghost_p90": None, "ghost_max": None}
    return {"ghost_mean": float(s.mean()), "ghost_p90": float(np.percentile(s, 90)), "ghost_max": float(s.max())}
