"""Child processes that do not outlive their parent: `die_with_parent` as a `subprocess` `preexec_fn`.

Linux's PR_SET_PDEATHSIG has the kernel signal the child when the thread that started it dies, however it dies
(SIGKILL, a crash, the bench's time limit), so no viewer, bench job or model step runs on unseen. Elsewhere it is
a no-op. It runs between fork and exec, so it only calls prctl: no locks, no threads, no allocation to speak of.
"""

from __future__ import annotations

import contextlib
import signal
import sys

PR_SET_PDEATHSIG = 1


def die_with_parent(sig: int = signal.SIGKILL) -> None:
    """In a child before exec: ask the kernel to send `sig` when the parent dies (Linux only)."""
    if sys.platform.startswith("linux"):
        import ctypes

        with contextlib.suppress(OSError, AttributeError):
            ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, sig)


def terminate_with_parent() -> None:
    """die_with_parent with SIGTERM (a process that should get the chance to close cleanly, such as a viewer)."""
    die_with_parent(signal.SIGTERM)
