"""The OpenDSS context's lifecycle: the only module that imports ``opendssdirect``.

:func:`new_context` makes a context whose creation and disposal hold :data:`DSS_LIFECYCLE` (a segfault
workaround, see their docstrings); :func:`compile_read_only` compiles a model without writing into its folder;
:func:`command` runs one OpenDSS command and turns OpenDSS's exception into an ``EngineError``. Everything else
reaches OpenDSS through a context made here (``engine.py``, ``circuit_tables.py``, ``circuit_survey.py``), never
through ``opendssdirect``'s global one.
"""

from __future__ import annotations

import gc
import os
import tempfile
import threading
from pathlib import Path

from simulator_bridge.errors import EngineError
from simulator_bridge.opendss.pinned_environ import pin

pin()  # before the library loads: it keeps a pointer to the C environment array (pinned_environ's docstring)

import opendssdirect as dss  # noqa: E402

__all__ = [
    "DSS_LIFECYCLE",
    "DssException",
    "LoadBatch",
    "close_debug_traces",
    "command",
    "compile_feeder",
    "compile_read_only",
    "new_context",
]

DssException = dss.DSSException
"""The exception OpenDSS's wrapper raises for a rejected command or a failed solution."""

_LOAD_SETTER_FLAGS = 2  # SetterFlags_AvoidFullRecalc: a kW change does not rebuild the load's Yprim
_BATCH_SET = 0  # BatchOperation_Set


def command(d, cmd: str, *, what: str) -> str:
    """Run ``cmd`` in context ``d`` and return OpenDSS's result text.

    Raises
    ------
    EngineError
        OpenDSS rejected the command; ``what`` says whose command it was.
    """
    try:
        d.Text.Command(cmd)
    except dss.DSSException as e:
        raise EngineError(f"{what}: OpenDSS rejected {cmd!r}: {e}; fix the command or the model") from e
    return d.Text.Result()


DSS_LIFECYCLE = threading.RLock()
"""Held while an OpenDSS context is created, compiled or disposed.

Contexts solve in parallel threads, but their birth and death are not safe to overlap: ``ctx_New`` segfaulted
once in CI in a bridge thread while the test's main thread let go of an earlier engine (cffi disposes a context
from whichever thread drops the last reference), and ``compile``/``redirect`` change the process's working
directory, so two compiles at once read each other's relative ``redirect`` files ("Redirect file not found",
reproduced with two threads compiling IEEE 13). Re-entrant: a disposal that the garbage collector starts inside
a locked section of the same thread goes through.
"""


def new_context():
    """A fresh OpenDSS context whose creation and disposal hold :data:`DSS_LIFECYCLE`.

    ``dss.NewContext()`` attaches ``ctx_Dispose`` to the context pointer as a bare cffi destructor; it is
    replaced by one that takes the lock, owned by the context's own API object (so it runs after that object's
    callbacks are unregistered, as before).

    The segfault in ``ctx_New`` that CI met three times (in a test's bridge thread) was not about threads: the
    library read the C environment through a pointer that glibc had freed (``pinned_environ``, applied when this
    module loads).
    """
    with DSS_LIFECYCLE:
        # The cyclic garbage collector disposes contexts left in reference cycles from whichever thread it runs
        # in; inside this section that is this thread, which holds the (re-entrant) lock, so a collection
        # triggered by the wrapper's own allocations would dispose an old context in the middle of creating the
        # new one (the segfault in ctx_New seen twice in test_bridge, right after a fixture dropped an engine).
        # Collect first, then keep the collector off while the context is made.
        gc.collect()
        enabled = gc.isenabled()
        gc.disable()
        try:
            d = dss.NewContext()
        finally:
            if enabled:
                gc.enable()
    util = d._api_util
    ffi, lib = util.ffi, util.lib_unpatched
    ffi.gc(util.ctx, None)  # detach the unlocked destructor
    util._cvvc_disposer = ffi.gc(util.ctx, _locked_dispose(lib))
    return d


def _locked_dispose(lib):
    def dispose(ctx) -> None:
        with DSS_LIFECYCLE:
            lib.ctx_Dispose(ctx)
    return dispose


def compile_feeder(d, master: Path, extra_commands: tuple[str, ...] | list[str] = ()) -> None:
    """Compile ``master`` into ``d`` (read only, see :func:`compile_read_only`; the working directory is restored),
    run ``extra_commands``, and turn its RegControls' debug traces off. Call it holding :data:`DSS_LIFECYCLE`.

    Raises
    ------
    EngineError
        The model does not compile, an extra command is rejected, or the model compiles to an empty circuit.
    """
    cwd = os.getcwd()
    try:
        compile_read_only(d, master)
        for cmd in extra_commands:
            d.Text.Command(cmd)
    except dss.DSSException as e:
        raise EngineError(f"{master}: the feeder does not compile: {e}; fix the OpenDSS model") from e
    finally:
        os.chdir(cwd)
    if d.Circuit.NumBuses() == 0:
        raise EngineError(f"{master}: compiled to an empty circuit; is this an OpenDSS master file?")
    close_debug_traces(d)


def compile_read_only(d, master: Path) -> None:
    """Compile ``master`` without writing into its folder, then make its folder the data path as ``compile`` does.

    ``compile`` makes the master's folder OpenDSS's output folder while the model is read, so a model that opens
    an output file as it is defined (epri-ckt24's LTC has ``debugtrace=yes``: ``REG_<name>.csv``) writes into the
    shared, read-in-place model folder, and FreePascal's exclusive lock on that file makes every other process that
    compiles the model meanwhile fail ("Unable to create file"). Here the model is read with ``redirect`` (which
    resolves its files as ``compile`` does) while the data path is a private temporary folder, removed afterwards.
    """
    with tempfile.TemporaryDirectory(prefix="cvvc-dss-") as scratch:
        d.Text.Command(f'set datapath="{scratch}"')
        d.Text.Command(f'redirect "{master}"')
        close_debug_traces(d)  # closes the trace files, which live in scratch
        d.Text.Command(f'set datapath="{master.parent}"')


def close_debug_traces(d) -> None:
    """Turn off every RegControl's ``debugtrace``, which closes its trace file.

    A model compiled with ``debugtrace=yes`` (epri-ckt24's LTC) keeps ``REG_<name>.csv`` open in the model's
    folder; a second context in the same process then fails to compile it ("Unable to create file").
    """
    i = d.RegControls.First()
    while i > 0:
        d.Text.Command(f"edit regcontrol.{d.RegControls.Name()} debugtrace=no")
        i = d.RegControls.Next()


class LoadBatch:
    """A DSS C-API batch handle over every load of context ``d``: kW and kvar of all loads set in two calls.

    Parameters
    ----------
    d : the context. names : every load's name, in ``Loads.First/Next`` (class) order, which is the batch's.

    Raises
    ------
    EngineError
        The batch does not hold as many loads as ``names`` (a broken context).
    """

    def __init__(self, d, names: tuple[str, ...]) -> None:
        ffi, lib = d.dss_ffi, d.dss_lib
        self._ffi, self._lib = ffi, lib
        self._ptr = ffi.new("void***")
        dims = ffi.new("int32_t[4]")
        lib.Batch_CreateByClassS(self._ptr, dims, b"Load")
        self.n_loads = int(dims[0])
        if self.n_loads != len(names):
            raise EngineError(f"internal: load batch has {self.n_loads} loads, Loads has {len(names)}")
        if names:
            d.Circuit.SetActiveElement(f"Load.{names[0]}")
            props = [p.lower() for p in d.Element.AllPropertyNames()]
            self._kw_prop, self._kvar_prop = props.index("kw") + 1, props.index("kvar") + 1

    def set(self, p_kw, q_kvar) -> None:
        """Set every load's kW and kvar (contiguous float arrays in batch order) [kW], [kvar]; the loads' Yprim is
        not rebuilt for it.
        """
        batch = self._ptr[0]
        self._lib.Batch_Float64Array(batch, self.n_loads, self._kw_prop, _BATCH_SET,
                                     self._ffi.from_buffer("double[]", p_kw), _LOAD_SETTER_FLAGS)
        self._lib.Batch_Float64Array(batch, self.n_loads, self._kvar_prop, _BATCH_SET,
                                     self._ffi.from_buffer("double[]", q_kvar), _LOAD_SETTER_FLAGS)

    def close(self) -> None:
        """Release the batch handle (once; later calls do nothing)."""
        if self._ptr is not None and self._ptr[0] != self._ffi.NULL:
            self._lib.Batch_Dispose(self._ptr[0])
            self._ptr = None
