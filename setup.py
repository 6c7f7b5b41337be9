"""Build step: compile the numba kernels ahead of time, one extension module per kernel source.

Everything else about the package is in ``pyproject.toml``. Each kernel source (Relative Point's
``relpoint/estimators/relative_point/_kernels.py``, FastSLAM's ``relpoint/estimators/_fastslam_kernels.py``)
names each kernel's argument types (:mod:`relpoint._aot_kernels`); numba's ``pycc`` turns them into an
ordinary extension module beside the source, named after it with ``_aot`` appended, so a fresh
install's first run starts without compiling. Each extension is optional: if it cannot be built (no
C compiler, an unsupported numba), the install goes on and those kernels are compiled on their
first call, as before.
"""

from __future__ import annotations

import importlib.util
import os
import sys
import tempfile
from pathlib import Path
from types import ModuleType

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext
from setuptools.modified import newer_group

ROOT = Path(__file__).parent
CORE = "relpoint/_aot_kernels.py"
KERNEL_SOURCES = (
    "relpoint/estimators/relative_point/_kernels.py",
    "relpoint/estimators/_fastslam_kernels.py",
    "relpoint/estimators/dense/_kernels.py",
)
EXTENSIONS = {source.removesuffix(".py").replace("/", ".") + "_aot": source for source in KERNEL_SOURCES}
"""Dotted name of each prebuilt extension module: its kernel source."""


def _load(name: str, path: Path) -> ModuleType:
    """Execute ``path`` as module ``name`` without importing its packages (they need the run-time dependencies)."""
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def _kernel_compiler(extension: str):  # -> numba.pycc.CC
    """A pycc compiler with every kernel of ``extension``'s source (and its source digest) exported."""
    if "relpoint._aot_kernels" not in sys.modules:  # the first extension: set up once
        os.environ["RELPOINT_KERNELS"] = "jit"  # the source modules must hand out numba dispatchers
        # Cached machine code names the module it was compiled in: keep these copies' out of the package's cache.
        os.environ["NUMBA_CACHE_DIR"] = tempfile.mkdtemp(prefix="relpoint-kernels-build-")
        _load("relpoint._aot_kernels", ROOT / CORE)
    source = ROOT / EXTENSIONS[extension]
    module = _load(extension.removesuffix("_aot") + "_source", source)
    kernels = module.kernels
    if kernels.prebuilt_name != extension:
        raise ValueError(f"{source.name} names its prebuilt module {kernels.prebuilt_name}, not {extension}")

    from numba.core import sigutils
    from numba.pycc import CC

    compiler = CC(extension.rpartition(".")[2], module)
    compiler.output_dir = str(source.parent)
    for kernel, argument_types in kernels.signatures.items():
        dispatcher = getattr(module, kernel)
        arguments, _ = sigutils.normalize_signature(f"({argument_types},)")
        dispatcher.compile(arguments)
        returned = dispatcher.overloads[arguments].signature.return_type
        compiler.export(kernel, returned(*arguments))(dispatcher.py_func)
    digest = kernels.source_digest()

    def source_digest() -> int:  # the digest is frozen into the machine code as a constant
        return digest

    compiler.export("source_digest", "i8()")(source_digest)
    return compiler


class BuildKernels(build_ext):
    """build_ext that first has numba write each kernel module's object file; any failure leaves them to the JIT.

    It does what ``CC.distutils_extension`` sets up, but only when the extension is built, so that
    reading ``setup.py`` (metadata, sdists) compiles nothing.
    """

    def build_extension(self, ext) -> None:
        if ext.name not in EXTENSIONS:
            return super().build_extension(ext)
        if not (self.force or newer_group([str(ROOT / path) for path in ext.depends], self.get_ext_fullpath(ext.name))):
            return
        try:
            compiler = _kernel_compiler(ext.name)
            ext.sources = compiler._get_mixin_sources()
            ext.define_macros = compiler._get_mixin_defines()
            ext.include_dirs = compiler._toolchain.get_python_include_dirs()
            ext.extra_link_args = compiler._get_extra_ldflags()
            build_temp = Path(self.build_temp) / ext.name
            build_temp.mkdir(parents=True, exist_ok=True)
            objects, _ = compiler._compile_object_files(str(build_temp))
            ext.extra_objects = objects
            super().build_extension(ext)
        except Exception as error:  # an optional speed-up: report (on one line) and go on
            reason = " ".join(str(error).split())
            message = f"relpoint: {ext.name} not compiled ahead of time ({reason}); its kernels compile on first use"
            print(message, file=sys.stderr)


setup(
    ext_modules=[
        Extension(name, sources=[], depends=[source, CORE], optional=True) for name, source in EXTENSIONS.items()
    ],
    cmdclass={"build_ext": BuildKernels},
)
