"""Types of the compiled elementary functions (`_libm.cpp`); `kneeseat_core.libm` uses it."""
from typing import Any

def elementwise(name: str, x: Any, p: float = ...) -> bytes: ...
