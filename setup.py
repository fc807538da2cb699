"""Build of the C extension only; every other piece of metadata lives in pyproject.toml.

``rt_runtime.planning._verify`` is the verifier kernel (``rt_runtime/planning/kernel/``: one C
unit per job, see ``kernel.h`` for why it is C). ``pip install -e .`` compiles it in place with
the machine's C compiler, which the install needs: the planner's fill, retiming and back-off
searches exist only in C (design notes, "A C compiler is required"). Without one the install
fails and says so.
"""

from glob import glob

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext

KERNEL = "rt_runtime/planning/kernel"
SOURCES = sorted(glob(f"{KERNEL}/*.c"))
HEADERS = sorted(glob(f"{KERNEL}/*.h"))

# -O3 (it vectorises plan's trig and rotation loops: 2.5 us less per row) and strict IEEE
# arithmetic: parity with the numpy reference needs no -ffast-math and no FMA contraction;
# -fno-math-errno only drops errno writes; -fno-trapping-math lets the compiler compute both
# sides of a select (the soil force of the dynamics loops, ~2 us less per plan with AVX2): it
# changes no value, only when floating-point exception flags would be raised, which nothing reads.
# -fvisibility=hidden: the units' functions stay inside each module (only PyInit_* is exported).
FLAGS = [
    "-O3", "-std=c99", "-ffp-contract=off", "-fno-math-errno", "-fno-trapping-math",
    "-fvisibility=hidden",
]  # fmt: skip


class BuildKernel(build_ext):  # type: ignore[misc]  # setuptools is untyped here
    """build_ext that names the missing C compiler instead of a bare compiler traceback, and
    skips only the optional AVX2 build where the compiler cannot target it."""

    def build_extension(self, ext: Extension) -> None:
        try:
            super().build_extension(ext)
        except Exception as exc:  # CompileError, LinkError, a missing executable (OSError)
            if ext.name.endswith("_avx2"):
                self.warn(f"skipping {ext.name} (the baseline kernel serves every CPU): {exc}")
                return
            raise SystemExit(
                f"error: building {ext.name} needs a C99 compiler (gcc or cc, found through CC "
                "or the Python build's default) and the Python headers (python3-dev); "
                f"it failed: {exc}"
            ) from exc


setup(
    cmdclass={"build_ext": BuildKernel},
    ext_modules=[
        Extension(
            "rt_runtime.planning._verify",
            sources=SOURCES,
            depends=HEADERS,
            extra_compile_args=FLAGS,
            libraries=["m"],
        ),
        # The same kernel for CPUs with AVX2 (4 doubles per vector: plan ~23 % faster, the
        # same results bit for bit); verify.py picks it at run time where the CPU has AVX2. A
        # compiler without -mavx2 (another architecture) skips it.
        Extension(
            "rt_runtime.planning._verify_avx2",
            sources=SOURCES,
            depends=HEADERS,
            extra_compile_args=[*FLAGS, "-mavx2"],
            define_macros=[("VK_AVX2", "1")],
            libraries=["m"],
        ),
    ],
)
