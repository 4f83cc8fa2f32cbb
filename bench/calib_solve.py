#!/usr/bin/env python3
"""Multi-position calibration solve time (target: < 50 ms for 26 poses x 2000 samples).

From raw samples to parameters: per-pose mean and uncertainty (calib.static.interval_stats),
the six-position pre-calibration on the faces, then the |a| = g nonlinear fit with its
covariance (calib.accel.multi_position). Synthetic poses from a random truth with the
ADXL355's noise at 500 Hz. Reports the median of repeated solves and how the time grows with
the number of poses and of samples per pose. Prints a final JSON line.

    python bench/calib_solve.py [--no-publish]

Prints the markdown table README states and publishes it (bench/publish.py).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "host"))

import numpy as np  # noqa: E402
from imubench.calib import accel as CA  # noqa: E402
from imubench.calib.static import interval_stats  # noqa: E402
from imubench.units import G0_MPS2  # noqa: E402
sys.path.insert(0, str(Path(__file__).resolve().parent))
from publish import add_arguments, publish  # noqa: E402

FS = 500.0
NOISE = 22.5e-6 * G0_MPS2 * np.sqrt(FS)


def poses(n_poses: int, n_samples: int, rng) -> list[np.ndarray]:
    m = np.eye(3) + rng.normal(0, 0.005, (3, 3))
    b = rng.normal(0, 0.1, 3)
    plan = np.array([p.direction for p in CA.POSE_PLAN])     # 6 faces, 12 edges, 8 corners
    subsets = {14: list(range(6)) + list(range(18, 26)),     # faces + corners
               18: list(range(18))}                          # faces + edges
    dirs = plan[subsets[n_poses]] if n_poses in subsets else plan
    if n_poses > len(dirs):
        extra = rng.normal(size=(n_poses - len(dirs), 3))
        dirs = np.vstack([dirs, extra / np.linalg.norm(extra, axis=1)[:, None]])
    dirs = dirs[:n_poses]
    return [(G0_MPS2 * d) @ m.T + b + rng.normal(0, NOISE, (n_samples, 3)) for d in dirs]


def solve(samples: list[np.ndarray]):
    stats = [interval_stats(s) for s in samples]
    means = np.array([s[0] for s in stats])
    sig = np.array([s[2] for s in stats])
    faces = [i for i, mu in enumerate(means) if np.max(np.abs(mu)) / np.linalg.norm(mu) > 0.95]
    init = CA.six_position(means[faces], sig[faces]) if len(faces) >= 6 else None
    return CA.multi_position(means, sig, init=init)


def timed(n_poses: int, n_samples: int, repeat: int = 15) -> float:
    rng = np.random.default_rng(n_poses * 1000 + n_samples)
    data = poses(n_poses, n_samples, rng)
    solve(data)                                    # warm-up (imports, caches)
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        solve(data)
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts))


def table(base: float, by_poses: dict[int, float], by_samples: dict[int, float]) -> str:
    def ms(ts) -> str:
        return " / ".join(f"{t * 1e3:.0f}" for t in ts) + " ms"
    return ("| case | time |\n|---|---|\n"
            f"| 26 poses × 2000 samples (target < 50 ms) | {ms([base])} |\n"
            f"| {' / '.join(map(str, by_poses))} poses × 2000 samples | {ms(by_poses.values())} |\n"
            f"| 26 poses × {' / '.join(map(str, by_samples))} samples | {ms(by_samples.values())} |\n")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_arguments(ap)
    a = ap.parse_args()
    base = timed(26, 2000)
    by_poses = {n: timed(n, 2000) for n in (14, 18, 26, 52)}
    by_samples = {n: timed(26, n) for n in (500, 2000, 8000, 32000)}
    print(f"26 poses x 2000 samples: {base * 1e3:.1f} ms (target < 50 ms: {'MET' if base < 0.05 else 'MISSED'})")
    print("poses (2000 samples each; 14 = faces+corners, 18 = faces+edges): " + ", ".join(f"{n}: {t * 1e3:.1f} ms" for n, t in by_poses.items()))
    print("samples per pose (26 poses): " + ", ".join(f"{n}: {t * 1e3:.1f} ms" for n, t in by_samples.items()))
    md = table(base, by_poses, by_samples)
    print("\n" + md, end="")
    publish("calib_solve", md, {"median of": "15 solves"}, enabled=not a.no_publish)
    print(json.dumps({"solve_ms_26x2000": round(base * 1e3, 2), "target_ms": 50, "met": base < 0.05,
                      "ms_by_poses": {k: round(v * 1e3, 2) for k, v in by_poses.items()},
                      "ms_by_samples": {k: round(v * 1e3, 2) for k, v in by_samples.items()}}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
