"""Progress display: a one-line bar on a terminal, plain log lines otherwise."""
import sys
import time


class Progress:
    def __init__(self, start, end, dt, n, compile_s, enabled=None, stream=sys.stderr):
        self.start, self.end, self.dt, self.n = start, end, dt, n
        self.stream = stream
        self.tty = hasattr(stream, "isatty") and stream.isatty()
        self.enabled = (enabled if enabled is not None else True)
        self.t0 = time.perf_counter()
        self.last = self.t0
        self.last_pct = -1
        self.elapsed = 0.0
        if self.enabled and compile_s is not None:
            self._emit(f"compile/load of kernels: {compile_s:.2f} s", newline=True)

    def _emit(self, text, newline=False):
        if self.tty and not newline:
            self.stream.write("\r" + text[:120].ljust(120))
        else:
            self.stream.write(text + "\n")
        self.stream.flush()

    def update(self, step):
        now = time.perf_counter()
        self.elapsed = now - self.t0
        if not self.enabled:
            return
        done = step - self.start
        total = max(self.end - self.start, 1)
        pct = int(100 * done / total)
        if self.tty:
            if now - self.last < 0.2 and step < self.end:
                return
        elif pct // 10 == self.last_pct // 10 and step < self.end:
            return
        self.last, self.last_pct = now, pct
        rate = done / self.elapsed if self.elapsed > 0 else 0.0
        eta = (self.end - step) / rate if rate > 0 else float("nan")
        bar = "#" * (pct // 5) + "." * (20 - pct // 5)
        self._emit(f"[{bar}] {pct:3d}% t = {step * self.dt:.4g} s  {rate:.0f} steps/s  "
                   f"{rate * self.n:.3g} particle-steps/s  ETA {eta:.0f} s")

    def close(self):
        self.elapsed = time.perf_counter() - self.t0
        if self.enabled and self.tty:
            self.stream.write("\n")
            self.stream.flush()
