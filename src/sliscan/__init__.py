"""sliscan: single-shot structured-light 3D scanning with the Gray code composite pattern."""

from sliscan._validate import InputError
from sliscan.pipeline import Scanner, scan
from sliscan.types import Calibration, Device, PatternSpec, ScanResult

__version__ = "0.1.0"

__all__ = ["Calibration", "Device", "InputError", "PatternSpec", "ScanResult", "Scanner", "__version__", "scan"]
