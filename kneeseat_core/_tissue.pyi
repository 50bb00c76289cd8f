"""Types of the compiled tissue rates (`_tissue.cpp`); `kneeseat_core.ligaments` uses it."""
from typing import Any

def pushes(seg_local: Any, seg_sign: Any, seg_fixed: Any, seg_fibre: Any, slack: Any,
           stiffness: Any, transition: Any, poses: Any) -> tuple[bytes, bytes]: ...
