"""kneeseat core: settle rigid bodies by collision detection (US 6,708,142); no ROS."""
from __future__ import annotations

__all__ = ['kneeseat_version']


def kneeseat_version() -> str:
    """The installed kneeseat version ('unknown' when not installed as a distribution).

    Tables record it; a Dask build checks that every worker runs the same one.
    """
    # importlib.metadata scans the installed distributions: only tables and Dask builds ask
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version('kneeseat_ros')
    except PackageNotFoundError:
        return 'unknown'
