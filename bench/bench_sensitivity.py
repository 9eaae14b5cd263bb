"""Benchmarks of the batched force-sensitivity study (docs/sensitivity.md).

- ``sensitivity_configs``: rig configurations per second on one core, each a random cubic rig
  (k1, k2, k3, Z) built by the vectorised geometry, its structure matrix, the singularity screen and
  S (paper eq. 12) for one wrench, i.e. two tension distributions (T0, Tw) with the ``exact``
  method.  Peer: the per-configuration loop a user would write (``cubic_rig`` + ``structure_matrix``
  + ``gravity_wrench`` + ``distribute`` twice per configuration) on a subset, same run.
- ``sensitivity_configs_penalty``: the same with the paper's penalty method.
- ``sensitivity_paper_cubic_960_s``: seconds for the paper's 960-case cubic study (80 geometries x
  6 forces x 2 directions, ``exact``); peer: the per-configuration loop over the same 960 cases.
"""

from __future__ import annotations

import os
import time

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import numpy as np  # noqa: E402


def _best(fn, repeat: int = 3) -> float:  # type: ignore[no-untyped-def]
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def _configs(n: int, rng: np.random.Generator) -> np.ndarray:
    k = np.sort(rng.uniform(0.025, 0.4, size=(n, 3)), axis=1)[:, ::-1]
    Z = rng.uniform(0.45, 0.95, size=n)
    return np.column_stack([k, Z])


def run() -> dict[str, dict]:
    from cdpr.analysis import rigs
    from cdpr.analysis import sensitivity as sens
    from cdpr.analysis.dynamics import gravity_wrench
    from cdpr.analysis.kinematics import structure_matrix
    from cdpr.analysis.tension import distribute
    from cdpr.pipelines.sensitivity_report import StudyOptions, _cubic_grid, cubic_loads

    rng = np.random.default_rng(1)
    W = np.array([60.949, 0.0, 0.0, 0.0, 0.0, 0.0])
    G = sens.gravity_load(5.0)

    def batched(cfg: np.ndarray, method: str) -> np.ndarray:
        A = sens.structure_matrices(
            sens.cubic_geometry(cfg[:, 0], cfg[:, 1], cfg[:, 2], Z_m=cfg[:, 3])
        )
        return sens.sensitivity(A, W, G, 35.0, 1000.0, method).S_N

    def loop(cfg: np.ndarray, loads: np.ndarray, method: str) -> np.ndarray:
        out = np.empty((len(cfg), len(loads)))
        for i, (k1, k2, k3, Z) in enumerate(cfg):
            rig = rigs.cubic_rig(k1, k2, k3, Z_m=Z)
            A = structure_matrix(
                rig.anchors_O_m, rig.attach_P_m, rig.reference_position_O_m, np.eye(3)
            )
            Gi = gravity_wrench(rig.mass_kg, rig.com_P_m, np.eye(3), rig.gravity_O_mps2)
            for j, Wj in enumerate(loads):
                T0 = distribute(method, A, -Gi, rig.t_min_N, rig.t_max_N).tensions_N
                Tw = distribute(method, A, -(Gi + Wj), rig.t_min_N, rig.t_max_N).tensions_N
                out[i, j] = np.linalg.norm(T0 - Tw) / 8
        return out

    results: dict[str, dict] = {}
    for name, method, n, n_peer in (
        ("sensitivity_configs", "exact", 100_000, 300),
        ("sensitivity_configs_penalty", "penalty", 20_000, 100),
    ):
        cfg = _configs(n, rng)
        t = _best(lambda cfg=cfg, method=method: batched(cfg, method), 3)
        sub = cfg[:n_peer]
        tp = _best(lambda sub=sub, method=method: loop(sub, W[None], method), 1)
        # Same numbers either way (the test suite checks this too).
        np.testing.assert_allclose(
            batched(sub, method), loop(sub, W[None], method)[:, 0], rtol=1e-5, atol=1e-9
        )
        results[name] = {
            "value": n / t,
            "unit": "configs/s",
            "peer": f"per-configuration loop (cubic_rig + structure_matrix + distribute x2), {method}",
            "peer_value": n_peer / tp,
            "target": ">= 100000" if method == "exact" else None,
            "context": f"{n} random cubic rigs (k1, k2, k3, Z), one wrench, method {method}, 1 thread",
        }

    o = StudyOptions()
    grid = np.array(list(_cubic_grid(o.cubic)))
    loads, _, _ = cubic_loads(o.cubic.forces_N)

    def study() -> np.ndarray:
        A = sens.structure_matrices(sens.cubic_geometry(grid[:, 0], grid[:, 1], grid[:, 2]))
        return sens.sensitivity(A[:, None], loads, G, 35.0, 1000.0, "exact").S_N

    t960 = _best(study, 5)
    cfg960 = np.column_stack([grid, np.full(len(grid), 0.7)])
    tp960 = _best(lambda: loop(cfg960, loads, "exact"), 1)
    results["sensitivity_paper_cubic_960_s"] = {
        "value": t960,
        "unit": "s",
        "peer": "per-configuration loop over the same 960 cases (exact)",
        "peer_value": tp960,
        "target": "< 0.1 s",
        "context": f"{len(grid)} geometries x {len(loads)} loads = {len(grid) * len(loads)} cases, "
        "structure matrices, singularity screen, T0 and Tw (exact), S",
    }
    return results


if __name__ == "__main__":
    for k, v in run().items():
        print(k, v)
