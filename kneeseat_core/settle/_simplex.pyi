"""Types of the compiled simplex (`_simplex.cpp`); `kneeseat_core.settle.model` uses it."""
from typing import Any

def maximise(a: Any, b: Any, cost: Any) -> bytes: ...
