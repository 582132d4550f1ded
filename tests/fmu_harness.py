"""A small FMI 3.0 host for tests: one instance through FMPy, log messages captured.

Kept deliberately plain (no orchestrator) so FMU tests exercise the FMU alone.
"""
from __future__ import annotations

import shutil
import tempfile
from contextlib import contextmanager

import numpy as np
from fmpy import extract, read_model_description
from fmpy.fmi3 import FMU3Slave


class FmuInstance:
    def __init__(self, fmu_path, instance_name="instance", unzipdir=None):
        self.md = read_model_description(str(fmu_path))
        self._owns_dir = unzipdir is None
        self.unzipdir = unzipdir or extract(str(fmu_path), tempfile.mkdtemp(prefix="fmu_test_"))
        self.vars = {v.name: v for v in self.md.modelVariables}
        self.messages: list[tuple[int, str]] = []

        def log(env, status, category, message):
            self.messages.append((int(status), message.decode() if isinstance(message, bytes) else str(message)))

        self._callback = log
        self.slave = FMU3Slave(guid=self.md.guid, unzipDirectory=self.unzipdir,
                               modelIdentifier=self.md.coSimulation.modelIdentifier, instanceName=instance_name)
        self.slave.instantiate(loggingOn=True, logMessage=log)

    def vr(self, name):
        return [self.vars[name].valueReference]

    def size(self, name):
        return int(np.prod(self.vars[name].shape)) if self.vars[name].dimensions else 1

    def set(self, name, values):
        """Set a variable; a structural parameter is set in Configuration Mode, as the standard asks."""
        if self.vars[name].causality == "structuralParameter":
            self.slave.enterConfigurationMode()
            try:
                self._set(name, values)
            finally:
                self.slave.exitConfigurationMode()
        else:
            self._set(name, values)

    def _set(self, name, values):
        kind = self.vars[name].type
        values = np.atleast_1d(values).ravel().tolist()
        if kind == "Float64":
            self.slave.setFloat64(self.vr(name), values)
        elif kind == "Int32":
            self.slave.setInt32(self.vr(name), [int(v) for v in values])
        elif kind == "UInt64":
            self.slave.setUInt64(self.vr(name), [int(v) for v in values])
        elif kind == "String":
            self.slave.setString(self.vr(name), [str(v) for v in values])
        else:
            raise TypeError(kind)

    def get(self, name):
        kind = self.vars[name].type
        n = self.size(name)
        getter = {"Float64": self.slave.getFloat64, "Int32": self.slave.getInt32,
                  "UInt64": self.slave.getUInt64}[kind]
        if n > 1:
            return np.array(getter(self.vr(name), nValues=n))
        return getter(self.vr(name))[0]

    def outside_range(self, name, value) -> bool:
        """Whether ``value`` lies outside the variable's declared min/max (the FMU refuses the set)."""
        variable = self.vars[name]
        if variable.type not in ("Float64", "Int32", "UInt64"):
            return False
        low = float(variable.min) if variable.min is not None else -np.inf
        high = float(variable.max) if variable.max is not None else np.inf
        return bool(np.any(~((np.asarray(value, dtype=float) >= low) & (np.asarray(value, dtype=float) <= high))))

    def initialize(self):
        self.slave.enterInitializationMode()
        self.slave.exitInitializationMode()

    def expect_error(self, call, *words):
        """``call()`` must return fmi3Error (not fatal, not a crash) and log a reason with all words."""
        from fmpy.fmi1 import FMICallException

        try:
            call()
        except FMICallException as exc:
            assert exc.status == 3, f"expected fmi3Error, got status {exc.status}"
        else:
            raise AssertionError("the call succeeded; an error status was expected")
        assert any(all(w in m for w in words) for m in self.errors()), self.messages

    def expect_step_error(self, t, dt, *words):
        self.expect_error(lambda: self.slave.doStep(t, dt), *words)

    def errors(self):
        return [m for status, m in self.messages if status >= 3]

    def close(self):
        from fmpy.fmi1 import FMICallException

        try:
            self.slave.terminate()
        except FMICallException:
            # after an error the standard allows only fmi3Reset, fmi3SetFMUState and fmi3FreeInstance
            if not self.errors():
                raise
        finally:
            self.slave.freeInstance()
            self.slave.freeLibrary()
            if self._owns_dir:
                shutil.rmtree(self.unzipdir, ignore_errors=True)


@contextmanager
def fmu_instance(fmu_path, **kwargs):
    instance = FmuInstance(fmu_path, **kwargs)
    try:
        yield instance
    finally:
        instance.close()
