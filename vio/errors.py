"""One exception hierarchy. A user's mistake becomes one clear line on the command line, never a traceback."""

from __future__ import annotations


class VioError(Exception):
    """Base class of every error this project raises on purpose."""


class ConfigError(VioError):
    """A configuration file or `--set` override is invalid (unknown key, wrong type)."""


class CaptureError(VioError):
    """A capture is missing, malformed or inconsistent. The message names the file, the row and the problem."""

    def __init__(self, message: str, path: object | None = None, row: int | None = None) -> None:
        where = ""
        if path is not None:
            where = f"{path}"
            if row is not None:
                where += f":{row}"
            where += ": "
        super().__init__(f"{where}{message}")
        self.path = path
        self.row = row


class CalibrationError(VioError):
    """Calibration is missing or invalid."""


class EstimationError(VioError):
    """The estimator could not produce an estimate (for example, initialisation never succeeded)."""


class SimulationError(VioError):
    """A simulation scenario or trajectory file is invalid."""


class OutputError(VioError):
    """An output folder or file cannot be created or written (a file in the way, no permission, disk full)."""


class PartError(SimulationError):
    """A part model is invalid: a user's STL is missing, not an STL, empty, not watertight, or in unknown units."""


class ModelError(VioError):
    """The part model cannot be built or compared: no support plane or part found, a CAD or model file that is not
    a valid mesh, a model that does not overlap the CAD, a run without images."""
