"""What a phone accelerometer's axis errors cost the metric scale, and what `vio calibrate imu-axes` gets back
(issue 16), with the images out of the way: the IMU's own limit (`vio.bench.scale_shape`, perfect images) on 60 s
phone orbits simulated without images, per seed

- as simulated (`--camera phone`: scale factors, cross-axis terms, timestamp jitter),
- with the accelerometer's scale factors and cross-axis terms zeroed (the same noise draws and timestamps),
- as simulated, corrected with `vio calibrate imu-axes` fitted on a simulated tumble of the same phone
  (`vio simulate tumble --camera phone --seed S`: the device's errors come from their own stream of the seed).

    python -m vio.bench.imu_axes_limit --seeds 201-230 --out DIR

Writes the captures under DIR and DIR/imu_axes_limit.json; prints the table of docs/BENCHMARKS.md ("The phone
accelerometer's axes"). About 2 s per seed.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np
import yaml

VARIANTS = ("as simulated", "accelerometer axes zeroed", "corrected by imu-axes")


def parse_seeds(text: str) -> list[int]:
    """'201-230' or '201,205,207' -> seeds."""
    out: list[int] = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        out += list(range(int(a), int(b) + 1)) if b else [int(a)]
    return out


def one_seed(seed: int, folder: Path, duration_s: float = 60.0) -> dict:
    """The three scale errors (fractions) of one seed, and what is left of its accelerometer's axes after the
    correction (the larger of max |diag(K T) - 1| and half of max |(K T)^T (K T) - I|)."""
    from vio.bench.scale_shape import shape_scale
    from vio.calibrate.imu_axes import corrected, fit_acc_axes
    from vio.readers import open_capture
    from vio.sim.api import simulate
    from vio.sim.imu import PhoneImu
    from vio.sim.phone import simulate_options

    def orbit(name: str, imu: PhoneImu) -> Path:
        opts = simulate_options("phone")
        opts["phone_imu"] = imu
        out = folder / f"{name}_{seed}"
        return simulate("orbit", out, seed=seed, duration_s=duration_s, images=False, overwrite=True, **opts)

    plain = open_capture(orbit("orbit", PhoneImu()), needs=("imu",))
    zeroed = open_capture(orbit("noacc", PhoneImu(acc_scale=0.0, acc_misalignment=0.0)), needs=("imu",))
    tumble = simulate(
        "tumble", folder / f"tumble_{seed}", seed=seed, images=False, overwrite=True, **simulate_options("phone")
    )
    fit = fit_acc_axes(open_capture(tumble, needs=("imu",)).imu)
    T = np.asarray(yaml.safe_load((tumble / "scene" / "scene.yaml").read_text())["imu_errors"]["acc_T"], float)
    M = fit.correction @ T
    fixed = dataclasses.replace(plain, imu=corrected(plain.imu, fit.correction))  # the same capture, read once
    errors = [shape_scale(c).scale_error for c in (plain, zeroed, fixed)]
    left = max(float(np.abs(np.diag(M) - 1).max()), float(np.abs(M.T @ M - np.eye(3)).max()) / 2)
    return {"seed": seed, "scale_error": dict(zip(VARIANTS, errors, strict=True)), "axes_left": left}


def table(rows: list[dict]) -> str:
    lines = ["| phone IMU | median \\|scale error\\| | sd | mean |", "|---|---|---|---|"]
    for v in VARIANTS:
        e = np.array([r["scale_error"][v] for r in rows]) * 100
        lines.append(f"| {v} | {np.median(np.abs(e)):.3f} % | {e.std(ddof=1):.3f} % | {e.mean():+.3f} % |")
    left = np.array([r["axes_left"] for r in rows]) * 100
    lines.append(
        f"{len(rows)} seeds; the accelerometer's axes after the correction: median {np.median(left):.3f} %, "
        f"largest {left.max():.3f} %"
    )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    from vio.atomic import ensure_dir, write_json

    ap = argparse.ArgumentParser(prog="python -m vio.bench.imu_axes_limit", description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="201-230", help="e.g. 201-230 or 201,203 (default 201-230)")
    ap.add_argument("--out", required=True, help="folder for the captures and imu_axes_limit.json")
    args = ap.parse_args(argv)
    folder = ensure_dir(Path(args.out))
    rows = [one_seed(s, folder) for s in parse_seeds(args.seeds)]
    write_json(folder / "imu_axes_limit.json", {"rows": rows})
    print(table(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
