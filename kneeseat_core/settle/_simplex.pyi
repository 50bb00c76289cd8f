"""Types of the compiled simplex (`_simplex.cpp`); `kneeseat_core.settle.model` uses it."""
from typing import Any

def best_move(gaps: Any, slopes: Any, press: float, drive: Any, radius: Any) -> tuple[bytes, float]: ...
