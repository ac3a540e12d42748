"""oodrl's signal handler (cli.main) runs wherever the signal lands, an import included.

A signal that lands while the interpreter imports a module runs the handler inside importlib;
an import made by the handler then corrupts the outer import's bookkeeping (a KeyError naming the
thread, raised as the KeyboardInterrupt unwinds) or meets a module half made (logging's
"partially initialized module"), and the command ended as an "internal error" instead of
"interrupted". Where the signal lands is a matter of microseconds, so these tests check the two
properties that rule it out instead of hoping to hit the window: the handler imports only
modules already whole, and an error raised as the interrupt unwinds is reported as the interrupt.
"""

from __future__ import annotations

import builtins
import sys

import pytest

from oodrl import cli

IMPORT = builtins.__import__


def _refusing_import(name, *args, **kwargs):
    """An import of a module already whole passes (the interpreter's fast path: no import lock,
    no code run, as `warnings.filterwarnings`' own `import re`); any other fails the test."""
    module = sys.modules.get(name)
    if module is None or getattr(getattr(module, "__spec__", None), "_initializing", False):
        raise AssertionError(f"the signal handler imported {name}, which was not yet imported")
    return IMPORT(name, *args, **kwargs)


def test_settling_the_store_writes_imports_nothing_before_a_store_is_touched():
    """Signalled early (the command has not imported zarr, nor asyncio), the handler has no
    write to wait for and must not import what it would use to wait."""
    loaded = "zarr.core.sync" in sys.modules
    with pytest.MonkeyPatch.context() as patch:
        for name in ("zarr.core.sync", "asyncio", "concurrent.futures"):
            patch.delitem(sys.modules, name, raising=False)
        patch.setattr(builtins, "__import__", _refusing_import)
        cli._settle_store_writes()
    assert ("zarr.core.sync" in sys.modules) == loaded


def test_settling_the_store_writes_imports_nothing_with_a_write_in_flight():
    """With zarr's IO loop running and a coroutine pending on it, the handler waits for it
    (it finishes) without an import statement."""
    import asyncio
    import threading

    from zarr.core.sync import _get_loop

    loop = _get_loop()
    started, release, finished = threading.Event(), threading.Event(), threading.Event()

    async def write() -> None:
        started.set()
        await asyncio.get_running_loop().run_in_executor(None, release.wait, 5)
        finished.set()

    asyncio.run_coroutine_threadsafe(write(), loop)
    assert started.wait(5)
    threading.Timer(0.2, release.set).start()
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(builtins, "__import__", _refusing_import)
        cli._settle_store_writes()
    assert finished.is_set(), "the handler returned before the write in flight had landed"


def test_an_error_raised_while_an_interrupt_unwinds_is_the_interrupt():
    """A library's clean-up that fails because the signal cut it short (the error's context
    holds the KeyboardInterrupt) is reported as the interrupt; any other error is not."""
    try:
        try:
            raise KeyboardInterrupt
        finally:
            {}.pop(139664570715008)  # as importlib's `del _blocking_on[tid]`
    except KeyError as error:
        assert cli._raised_while_unwinding(error)

    try:
        try:
            raise ValueError("a bug")
        finally:
            {}.pop(1)
    except KeyError as error:
        assert not cli._raised_while_unwinding(error)
    assert not cli._raised_while_unwinding(RuntimeError("alone"))
