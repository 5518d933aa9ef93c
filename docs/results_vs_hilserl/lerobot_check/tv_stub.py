"""Stub for torchvision: the local torchvision 0.28.0 wheel fails to import with torch 2.13.0+cpu
(RuntimeError: operator torchvision::nms does not exist). Only image processing uses it; this run is state-only.
Any attribute is a dummy class; calling anything image-related would fail loudly."""
import importlib.abc
import importlib.machinery
import sys
import types


class _Dummy:
    def __init__(self, *a, **k):
        pass

    def __call__(self, *a, **k):
        raise RuntimeError("torchvision stub called (images not supported in this run)")


class _StubModule(types.ModuleType):
    def __getattr__(self, name):
        if name.startswith("__"):
            raise AttributeError(name)
        return type(name, (_Dummy,), {})


class _Finder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    def find_spec(self, fullname, path, target=None):
        if fullname == "torchvision" or fullname.startswith("torchvision."):
            return importlib.machinery.ModuleSpec(fullname, self, is_package=True)
        return None

    def create_module(self, spec):
        m = _StubModule(spec.name)
        m.__path__ = []
        m.__version__ = "0.0.0-stub"
        return m

    def exec_module(self, module):
        pass


sys.meta_path.insert(0, _Finder())
