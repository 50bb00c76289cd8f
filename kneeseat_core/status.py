"""How a settle ended: the codes a table stores per cell (part of the file format)."""
from __future__ import annotations

__all__ = ['Status', 'STATUS_NAMES', 'AT_REST', 'converged_share']


class Status:
    """Settle end codes; REST and CONSTRAINED are converged, the others are not."""

    REST = 0            # at rest (patent method: its stop rule)
    CONSTRAINED = 1     # at rest on the boundary of an envelope that holds
    ENVELOPE = 2        # the climb left the search envelope: no rest near the attitude
    LOST = 3            # lost contact: slid off the fixed body
    CAP = 4             # iteration cap
    WEDGED = 5          # the patent method's slide/rotate cycle
    FAILED = 6          # no contact along the push, or a start buried in the fixed body
    UNKNOWN = 7         # not converged, reason not recorded (tables written before codes)
    PULLED = 8          # its ligaments pull it off the fixed body against its load


STATUS_NAMES = {Status.REST: 'rest', Status.CONSTRAINED: 'rest on the envelope boundary',
                Status.ENVELOPE: 'left the search envelope', Status.LOST: 'lost contact',
                Status.CAP: 'iteration cap', Status.WEDGED: 'wedged (patent)',
                Status.FAILED: 'failed to settle', Status.UNKNOWN: 'not converged',
                Status.PULLED: 'pulled off by its ligaments'}

# the codes of a converged cell: the table claims it is at rest
AT_REST = (Status.REST, Status.CONSTRAINED)


def converged_share(converged: int, cells: int) -> str:
    """`converged` of `cells` as a percentage to a tenth, rounded down: "100.0%" only when
    every cell converged (3821 of 3822 reads 99.9%, not 100.0%), "0.0%" only when none did."""
    if cells <= 0:
        return '0.0%'
    tenths = 1000 * converged // cells
    if converged > 0 and tenths == 0:
        return '<0.1%'
    return f'{tenths // 10}.{tenths % 10}%'
