"""The C environment array OpenDSS's library captured stays valid while Python adds variables.

DSS C-API reads the environment through the ``environ`` pointer it copied when it was loaded; glibc reallocates
(frees) its own array when a variable is added, which made ``ctx_New`` segfault
(``simulator_bridge.opendss.pinned_environ``).
"""

from __future__ import annotations

import ctypes
import os
import subprocess
import sys

import pytest

pytestmark = [pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's environ (Linux only)"),
              pytest.mark.process]  # a child interpreter reads the environment


def _entries(address: int) -> list[bytes]:
    array = ctypes.cast(address, ctypes.POINTER(ctypes.c_char_p))
    out, i = [], 0
    while array[i] is not None:
        out.append(array[i])
        i += 1
    return out


def test_the_pinned_array_outlives_new_variables_and_the_environment_still_works():
    import simulator_bridge.opendss.dss_context  # noqa: F401 - loads the library after pinning
    from simulator_bridge.opendss.pinned_environ import _pinned

    assert _pinned, "the environment was not pinned before OpenDSS loaded"
    pinned = ctypes.addressof(_pinned[0])
    before = _entries(pinned)
    environ = ctypes.c_void_p.in_dll(ctypes.CDLL(None), "environ")
    added = [f"CVVC_PIN_TEST_{i}" for i in range(300)]
    try:
        for name in added:  # each a new variable: glibc grows (reallocates) its own array, never the pinned one
            os.environ[name] = "x" * 64
        assert environ.value != pinned  # glibc moved to an array of its own
        assert _entries(pinned) == before  # the pinned copy is intact (it was never freed or rewritten)
        child = subprocess.run([sys.executable, "-c", f"import os; print(os.environ['{added[-1]}'])"],
                               capture_output=True, text=True, check=True)
        assert child.stdout.strip() == "x" * 64  # the real environment has the new variables
    finally:
        for name in added:
            os.environ.pop(name, None)

