"""Wrench recovery and its covariance on the flat prototype rig, in poses per second.

Peer: the same formulas evaluated one pose at a time with numpy (what a script without batching does),
measured on a subset and reported per pose.  Both run in this process, single-threaded BLAS not forced.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from cdpr.analysis.kinematics import structure_matrix
from cdpr.analysis.rotations import rotation_from_euler
from cdpr.analysis.uncertainty import wrench_covariance
from cdpr.analysis.wrench import recover_wrench
from cdpr.pipelines.config import load_rig

RIG = Path(__file__).resolve().parents[1] / "data_samples" / "flat_optimum.toml"


def _best(fn, repeat: int = 3) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def run() -> dict[str, dict]:
    rig = load_rig(RIG)
    rng = np.random.default_rng(0)
    n = 100_000
    q = np.concatenate(
        [rig.reference_position_O_m + rng.normal(0, 0.005, (n, 3)), rng.normal(0, 0.01, (n, 3))],
        axis=1,
    )
    Tw = rng.uniform(100, 200, (n, 8))
    T0 = rng.uniform(100, 200, (n, 8))
    sd_q = np.array([5e-4] * 3 + [np.radians(0.1)] * 3)

    t_rec = _best(lambda: recover_wrench(rig, q, Tw, tare_tensions_N=T0))
    n_cov = 20_000
    t_cov = _best(
        lambda: wrench_covariance(
            rig, q[:n_cov], Tw[:n_cov], 0.05, sd_q, tare_tensions_N=T0[:n_cov]
        ),
        repeat=2,
    )

    k = 2000

    def loop() -> None:
        for i in range(k):
            A = structure_matrix(
                rig.anchors_O_m, rig.attach_P_m, q[i, :3], rotation_from_euler(q[i, 3:])
            )
            A @ (T0[i] - Tw[i])

    t_loop = _best(loop, repeat=2) / k
    return {
        "wrench_recovery_tare": {
            "value": n / t_rec,
            "unit": "poses/s",
            "peer": "per-pose loop of the same numpy formula",
            "peer_value": 1.0 / t_loop,
            "context": f"{n} poses, flat prototype rig, structure matrix + A (T0 - Tw)",
        },
        "wrench_covariance": {
            "value": n_cov / t_cov,
            "unit": "poses/s",
            "peer": None,
            "peer_value": None,
            "context": "tension + pose covariance (12 perturbed structure matrices per pose)",
        },
    }


if __name__ == "__main__":  # pragma: no cover
    for name, entry in run().items():
        print(name, entry)
