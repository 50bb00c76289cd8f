"""The node's diagnostics: what it counts, and the DiagnosticStatus it reports once a period.

`Counters` is plain Python: the node's hot path bumps its public counters directly (one
attribute each), and once per diagnostics period `window` closes the rate and latency
window and `recent_drops` says how many inputs were dropped within the sliding warning
window. Latency = node clock at publish - input stamp, in ms; unstamped inputs (stamp 0)
are counted in `unstamped` and left out of it. `status` turns the counters and what the
node serves into the one DiagnosticStatus 'kneeseat table_server': WARN while an input was
dropped within the warning window, ERROR once recording failed, else OK.
"""
from __future__ import annotations

from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass
import math

from diagnostic_msgs.msg import DiagnosticStatus
import numpy as np

from .conversions import diagnostic_status
from .served import Served
from .topics import STATUS_NAME

__all__ = ['Counters', 'NodeState', 'status']


class Counters:
    """Message counters of one node (attributes are read and bumped by the node)."""

    __slots__ = ('received', 'answered', 'published', 'clamped', 'nonconverged', 'unstamped',
                 'dropped', 'window_received', 'latencies_ns', '_window_start_ns', '_history')

    def __init__(self, reasons: tuple[str, ...], start_ns: int) -> None:
        """Args: reasons: the drop reasons, in display order; start_ns: node clock now."""
        self.received = 0
        self.answered = 0
        self.published = 0
        self.clamped = 0
        self.nonconverged = 0
        self.unstamped = 0
        self.dropped = dict.fromkeys(reasons, 0)
        self.window_received = 0             # answers in the current window
        self.latencies_ns: list[int] = []     # of the stamped answers in the window
        self._window_start_ns = start_ns
        self._history: deque[tuple[int, int]] = deque()   # (node ns, total dropped)

    def window(self, now_ns: int) -> tuple[float, float, float, float]:
        """(rate Hz, latency p50, p99, max ms) of the window ending now; starts a new one.

        The latencies are NaN when no stamped input was answered in the window.
        """
        window_s = max((now_ns - self._window_start_ns) * 1e-9, 1e-9)
        rate_hz = self.window_received / window_s
        lat = np.asarray(self.latencies_ns, dtype=np.float64) * 1e-6
        p50, p99, worst = ((float(np.percentile(lat, 50)), float(np.percentile(lat, 99)),
                            float(lat.max())) if lat.size else (math.nan,) * 3)
        self.window_received, self._window_start_ns, self.latencies_ns = 0, now_ns, []
        return rate_hz, p50, p99, worst

    def recent_drops(self, now_ns: int, dropped: int, window_s: float) -> int:
        """Inputs dropped within the last `window_s`, given `dropped` in total now: the total
        now less the total at the window's start (call once per diagnostics period)."""
        history = self._history
        horizon = now_ns - int(window_s * 1e9)
        history.append((now_ns, dropped))
        while len(history) > 1 and history[1][0] <= horizon:
            history.popleft()
        return dropped - (history[0][1] if history[0][0] <= horizon else 0)


@dataclass(frozen=True, slots=True)
class NodeState:
    """What the diagnostics say about the node besides its counters."""

    hardware_id: str                  # the node's fully qualified name
    out_of_range: str
    tracker_mode: bool
    tf_on: bool
    window_s: float                   # diagnostics_window_s
    recorder: str                     # 'off', 'recording DIR (N messages)' or 'error: ...'
    recording_failed: bool


def status(counters: Counters, dropped: Mapping[str, int], served: Served, node: NodeState,
           now_ns: int) -> DiagnosticStatus:
    """The node's DiagnosticStatus now; closes the counters' rate and latency window.

    Args:
        dropped: drops by reason, the pairer's unpaired and stale ones included.
    """
    rate_hz, p50, p99, worst = counters.window(now_ns)
    total = sum(dropped.values())
    recent = counters.recent_drops(now_ns, total, node.window_s)
    level, message = DiagnosticStatus.OK, 'serving'
    if recent:
        level = DiagnosticStatus.WARN
        message = f'{recent} inputs dropped in the last {node.window_s:g} s'
    if node.recording_failed:
        level, message = DiagnosticStatus.ERROR, 'recording failed; still serving'
    bounds = served.bounds_deg
    values: list[tuple[str, object]] = [
        ('table', str(served.path)),
        ('table_sha256', served.table.sha256),
        ('reference_frame', served.frame),
        ('bodies', ' '.join(served.bodies)),
        ('flexion_range_deg', f'{bounds.flexion_min_deg:.3f} {bounds.flexion_max_deg:.3f}'),
        ('varus_range_deg', f'{bounds.varus_min_deg:.3f} {bounds.varus_max_deg:.3f}'),
        ('out_of_range', node.out_of_range),
        ('mode', 'tracker' if node.tracker_mode else 'attitude'),
        ('tf', 'on' if node.tf_on else 'off'),
        ('received', counters.received),
        ('answered', counters.answered),
        ('published', counters.published),
        ('dropped', total),
        ('dropped_recent', recent),
        *((f'dropped_{reason}', n) for reason, n in dropped.items()),
        ('clamped', counters.clamped),
        ('nonconverged_answers', counters.nonconverged),
        ('unstamped', counters.unstamped),
        ('rate_hz', rate_hz),
        ('latency_p50_ms', p50),
        ('latency_p99_ms', p99),
        ('latency_max_ms', worst),
        ('recorder', node.recorder),
    ]
    return diagnostic_status(STATUS_NAME, level, message, node.hardware_id, values)
