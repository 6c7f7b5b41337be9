"""Build step: compile Relative Point's numba kernels ahead of time into ``_kernels_aot``.

Everything else about the package is in ``pyproject.toml``. The kernels' source,
``relpoint/estimators/relative_point/_kernels.py``, names each kernel's argument types; numba's
``pycc`` turns them into an ordinary extension module, so a fresh install's first run starts
without compiling. The extension is optional: if it cannot be built (no C compiler, an unsupported
numba), the install goes on and the kernels are compiled on their first call, as before.
"""

from __future__ import annotations

import importlib.util
import os
import sys
import tempfile
from pathlib import Path

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext
from setuptools.modified import newer

PACKAGE = "relpoint.estimators.relative_point"
KERNELS_SOURCE = "relpoint/estimators/relative_point/_kernels.py"
KERNELS = Path(__file__).parent / KERNELS_SOURCE
EXTENSION = "_kernels_aot"


def _kernel_compiler():  # -> numba.pycc.CC
    """A pycc compiler with every kernel of ``_kernels.py`` (and its source digest) exported."""
    os.environ["RELPOINT_KERNELS"] = "jit"  # the source module must hand out numba dispatchers
    # Cached machine code names the module it was compiled in: keep this copy's out of the package's cache.
    os.environ["NUMBA_CACHE_DIR"] = tempfile.mkdtemp(prefix="relpoint-kernels-build-")
    spec = importlib.util.spec_from_file_location(f"{PACKAGE}._kernels_source", KERNELS)
    kernels = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = kernels
    spec.loader.exec_module(kernels)

    from numba.core import sigutils
    from numba.pycc import CC

    compiler = CC(EXTENSION, kernels)
    compiler.output_dir = str(KERNELS.parent)
    for name, argument_types in kernels.SIGNATURES.items():
        dispatcher = getattr(kernels, name)
        arguments, _ = sigutils.normalize_signature(f"({argument_types},)")
        dispatcher.compile(arguments)
        returned = dispatcher.overloads[arguments].signature.return_type
        compiler.export(name, returned(*arguments))(dispatcher.py_func)
    digest = kernels.source_digest()

    def source_digest() -> int:  # the digest is frozen into the machine code as a constant
        return digest

    compiler.export("source_digest", "i8()")(source_digest)
    return compiler


class BuildKernels(build_ext):
    """build_ext that first has numba write the kernels' object file; any failure leaves them to the JIT.

    It does what ``CC.distutils_extension`` sets up, but only when the extension is built, so that
    reading ``setup.py`` (metadata, sdists) compiles nothing.
    """

    def build_extension(self, ext) -> None:
        if ext.name != f"{PACKAGE}.{EXTENSION}":
            return super().build_extension(ext)
        if not (self.force or newer(str(KERNELS), self.get_ext_fullpath(ext.name))):
            return
        try:
            compiler = _kernel_compiler()
            ext.sources = compiler._get_mixin_sources()
            ext.define_macros = compiler._get_mixin_defines()
            ext.include_dirs = compiler._toolchain.get_python_include_dirs()
            ext.extra_link_args = compiler._get_extra_ldflags()
            Path(self.build_temp).mkdir(parents=True, exist_ok=True)
            objects, _ = compiler._compile_object_files(self.build_temp)
            ext.extra_objects = objects
            super().build_extension(ext)
        except Exception as error:  # an optional speed-up: report and go on
            print(f"relpoint: kernels not compiled ahead of time ({error}); they compile on first use", file=sys.stderr)


setup(
    ext_modules=[Extension(f"{PACKAGE}.{EXTENSION}", sources=[], depends=[KERNELS_SOURCE], optional=True)],
    cmdclass={"build_ext": BuildKernels},
)
