"""Progress of the long phases (voxel preview, radius estimation, fit, topology rounds, subscans): a bar
or one line per phase.

On a terminal each phase shows a tqdm bar that ends with the reason it
stopped (a fit that converges after 57 of 80 iterations ends at 57/57,
"converged"). When stderr is not a terminal (redirected to a log file, a
batch job, a pipe, a notebook) no bar is drawn: each phase prints exactly
one plain summary line when it ends, e.g.
``BubSub fit: 57 iterations, 12.3 s, converged, f = 1.23e-03``; a phase made
with ``each=True`` (the subscans of ``bubsub reconstruct4d``, hours long)
also prints one line per finished step, so that a log shows how far it got.
``BUBSUB_PROGRESS=bar`` or ``=lines`` forces one of the two.

Every progress display of the clients goes through :func:`phase`: a tqdm bar
made elsewhere would write its carriage returns into log files.
"""

from __future__ import annotations

import os
import sys
import time

__all__ = ["phase", "Phase"]


def _use_bar(stream):
    mode = os.environ.get("BUBSUB_PROGRESS", "").strip().lower()
    if mode in ("bar", "lines"):
        return mode == "bar"
    isatty = getattr(stream, "isatty", None)
    return bool(isatty and isatty())


class Phase:
    """One phase's progress; make it with :func:`phase`.

    ``update(n, **postfix)`` after each step, ``close(reason)`` at the end
    (also when used as a context manager, with reason ``"interrupted"`` on
    Ctrl-C). Disabled phases do nothing.
    """

    def __init__(self, desc, total, unit, enabled, stream, each=False):
        from tqdm.auto import tqdm

        self.desc, self.total, self.unit = desc, total, unit
        self.enabled, self.stream, self.each = enabled, stream, each
        self.n = 0
        self.postfix = {}
        self.t0 = time.perf_counter()
        self.closed = False
        self.bar = None
        if enabled and _use_bar(stream):
            self.bar = tqdm(total=total, desc=desc, unit="it" if unit == "iteration" else unit, leave=True,
                            file=stream, dynamic_ncols=True)

    def __repr__(self):
        return f"phase({self.desc!r}, total={self.total!r}, unit={self.unit!r}, enabled={self.enabled!r})"

    def update(self, n=1, **postfix):
        self.n += n
        self.postfix.update(postfix)
        if self.bar is not None:
            self.bar.update(n)
            if postfix:
                self.bar.set_postfix(self.postfix)
        elif self.enabled and self.each and n:
            of = f" of {self.total}" if self.total else ""
            words = [f"{self.n}{of} done", f"{time.perf_counter() - self.t0:.1f} s"]
            print(f"{self.desc}: " + ", ".join(words + self._postfix_words()), file=self.stream, flush=True)

    def _postfix_words(self):
        return [f"{k} = {v}" for k, v in self.postfix.items()]

    def close(self, reason=None):
        """End the phase, stating why it stopped (``"converged"``, ``"iteration limit"``, ...)."""
        if self.closed or not self.enabled:
            self.closed = True
            return
        self.closed = True
        if self.bar is not None:
            if reason:
                # a phase that stopped early ends at its own count, not at e.g. 71 % of the limit
                self.bar.total = self.n
                self.bar.set_postfix_str(", ".join([reason] + [f"{k}={v}" for k, v in self.postfix.items()]))
            self.bar.close()
            return
        seconds = time.perf_counter() - self.t0
        words = [f"{self.n} {self.unit}{'s' if self.unit.isalpha() and self.n != 1 else ''}", f"{seconds:.1f} s"]
        if reason:
            words.append(reason)
        words += self._postfix_words()
        print(f"{self.desc}: " + ", ".join(words), file=self.stream, flush=True)

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        self.close("interrupted" if exc_type is KeyboardInterrupt else ("failed" if exc_type else None))


def phase(desc, total=None, *, unit="iteration", enabled=True, stream=None, each=False):
    """Progress of one phase: a bar on a terminal, else one summary line at its end.

    Parameters
    ----------
    desc : str
        E.g. ``"BubSub fit"``.
    total : int, optional
        Steps expected (the iteration limit).
    unit : str
        Name of a step.
    enabled : bool
        False: no output at all (``--quiet``).
    stream : file, optional
        Default ``sys.stderr``.
    each : bool
        Without a terminal, also one line per step (``subscans: 2 of 8 done,
        41.0 s, subscan = 5, bubbles = 34``), for phases of many long steps.

    Returns
    -------
    Phase
    """
    return Phase(desc, total, unit, enabled, sys.stderr if stream is None else stream, each=each)
