"""radiomap's compiled kernels (everything else is in pyproject.toml).

Two C extensions, ``mapping._ckernels`` (TSDF, display look-ups, depth pyramid) and ``radiometry._ckernels``
(uint8 correction, irradiance), the C twins of radiomap's Numba kernels: the same results without Numba's
~111 MB runtime in the process (docs/benchmarks.md). Built with OpenMP where the compiler has it, without
FMA contraction (results bit-identical to the Numba kernels). Both are optional: without a C compiler the
install goes on and radiomap runs its Numba kernels (``RADIOMAP_KERNELS`` chooses; ``mapping._native``).
"""

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext
from setuptools.errors import CCompilerError, ExecError, PlatformError


class BuildExt(build_ext):
    """Try each extension with OpenMP, then without; an extension that still fails is skipped (optional)."""

    def build_extension(self, ext):
        msvc = self.compiler.compiler_type == "msvc"
        base = ["/O2", "/fp:precise"] if msvc else ["-O3", "-ffp-contract=off", "-fno-fast-math"]
        openmp = (["/openmp"], []) if msvc else (["-fopenmp"], ["-fopenmp"])
        try:
            ext.extra_compile_args, ext.extra_link_args = base + openmp[0], list(openmp[1])
            super().build_extension(ext)
        except (CCompilerError, ExecError, PlatformError):
            print(f"radiomap: {ext.name} did not build with OpenMP; trying without (its kernels then run on one "
                  f"thread)")
            ext.extra_compile_args, ext.extra_link_args = base, []
            super().build_extension(ext)


setup(
    ext_modules=[
        Extension("mapping._ckernels", ["mapping/_ckernels.c"],
                  depends=["radiometry/_buffers.h", "radiometry/_simd_cpu.h", "mapping/_ckernels_raycast_simd.h"],
                  optional=True),
        Extension("radiometry._ckernels", ["radiometry/_ckernels.c"],
                  depends=["radiometry/_buffers.h", "radiometry/_simd_cpu.h", "radiometry/_ckernels_simd.h",
                           "radiometry/_ckernels_bucket.h"],
                  optional=True),
    ],
    cmdclass={"build_ext": BuildExt},
)
