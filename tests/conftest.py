"""Shared fixtures: the real data in ../shared/data (skipped when absent) and cached simulated captures."""

from __future__ import annotations

import signal
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = ROOT.parent / "shared" / "data"


def shared_path(*parts: str) -> Path:
    """Path inside ../shared/data; skips the calling test with a clear reason when it is absent."""
    p = SHARED_DATA.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"real data not available: {p} (the ../shared/data folder is only on the developers' machines)")
    return p


@pytest.fixture(scope="session")
def sim_capture(tmp_path_factory):
    """Factory: sim_capture(scenario, duration_s, imu, seed, images) -> capture folder, cached per session."""
    cache: dict[tuple, Path] = {}

    def make(
        scenario: str = "orbit",
        duration_s: float = 4.0,
        imu: str = "phone",
        seed: int = 0,
        images: bool = True,
    ) -> Path:
        key = (scenario, duration_s, imu, seed, images)
        if key not in cache:
            from vio.sim.api import simulate

            out = tmp_path_factory.mktemp("sim") / f"{Path(scenario).stem}_{imu}_{seed}_{duration_s:g}"
            cache[key] = simulate(scenario, out, seed=seed, duration_s=duration_s, imu_grade=imu, images=images)
        return cache[key]

    return make


def default_sigint() -> None:
    """In the child before exec: SIGINT back to its default, so Python turns it into KeyboardInterrupt even when the
    tests themselves run with SIGINT ignored (a shell's background job without job control ignores it)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
