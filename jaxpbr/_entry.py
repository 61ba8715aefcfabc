"""Start-up moments of the command line, for the tests.

`phase(name)` marks the moments of start-up ("start": the first statement of the package, before
NumPy and JAX are imported; "main": the start of `cli.main`): with `JAXPBR_TEST_PHASES` set to a
file, each name is appended to it as it is reached, and `JAXPBR_TEST_PAUSE=<name>` makes the
process wait at that moment (for a signal).
"""

import os
import time

__all__ = ["phase"]


def phase(name: str) -> None:
    """Test hook: report reaching `name` (JAXPBR_TEST_PHASES), wait there if JAXPBR_TEST_PAUSE names it."""
    path = os.environ.get("JAXPBR_TEST_PHASES")
    if not path:
        return
    with open(path, "a") as f:
        f.write(name + "\n")
    if os.environ.get("JAXPBR_TEST_PAUSE") == name:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            time.sleep(0.05)
