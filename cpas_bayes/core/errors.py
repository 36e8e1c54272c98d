"""The one exception type that reaches a user: bad input, said plainly.

Every refusal names the file, the place in it (row, column or key), what is
wrong and how to fix it. The CLI prints ``str(error)`` and exits non-zero; no
traceback reaches a user.
"""

from __future__ import annotations


class InputError(Exception):
    """Input the package refuses, with the file, the place, the problem and the fix."""

    def __init__(self, file, where, problem, fix):
        self.file = str(file)
        self.where = where
        self.problem = problem
        self.fix = fix
        super().__init__(self._message())

    def __reduce__(self):
        # Rebuilt from its four parts, so that a refusal raised in a worker process (a campaign's
        # step, a Monte Carlo batch) reaches the caller as itself, not as a failed unpickling.
        return (type(self), (self.file, self.where, self.problem, self.fix))

    def _message(self):
        place = f", {self.where}" if self.where else ""
        return f"{self.file}{place}: {self.problem}. Fix: {self.fix}"


class BundleError(InputError):
    """A flight-test bundle that does not follow the bundle format."""
