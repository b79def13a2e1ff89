"""Progress lines for long stages whose output goes to a log file.

tqdm's bar redraws in place, which a log file shows as one line per redraw or not at
all; these are plain lines like the trainers': done/total, seconds per item, ETA.
"""

from __future__ import annotations

import time


class ProgressLog:
    """``step()`` after each item; a line at most every ``every_s`` seconds, and at the end."""

    def __init__(self, total: int, what: str, every_s: float = 30.0, log=print):
        self.total, self.what, self.every_s, self.log = int(total), what, float(every_s), log
        self.done = 0
        self.started = self.last = time.perf_counter()

    def step(self, count: int = 1) -> None:
        self.done += count
        now = time.perf_counter()
        if now - self.last >= self.every_s or self.done >= self.total:
            self.last = now
            per = (now - self.started) / max(self.done, 1)
            eta = per * max(self.total - self.done, 0)
            self.log(f"{self.what}: {self.done}/{self.total}, {per:.2f} s each, elapsed {now - self.started:.0f} s, "
                     f"ETA {eta:.0f} s", flush=True)
