"""Build of the C extension only; every other piece of metadata lives in pyproject.toml.

``rt_runtime.planning._verify`` is the one-shot verifier kernel (see its source for why it is C).
``pip install -e .`` compiles it in place with the machine's C compiler. It is optional: without
a compiler the install still succeeds and ``rt_runtime.planning.verify.Verifier`` falls back to
the numpy reference (``backend="auto"``) or says how to build it (``backend="c"``).
"""

from setuptools import Extension, setup

# -O3 (it vectorises plan's trig and rotation loops: 2.5 us less per row) and strict IEEE
# arithmetic: parity with the numpy reference needs no -ffast-math and no FMA contraction;
# -fno-math-errno only drops errno writes; -fno-trapping-math lets the compiler compute both
# sides of a select (the soil force of the dynamics loops, ~2 us less per plan with AVX2): it
# changes no value, only when floating-point exception flags would be raised, which nothing reads.
FLAGS = ["-O3", "-std=c99", "-ffp-contract=off", "-fno-math-errno", "-fno-trapping-math"]

setup(
    ext_modules=[
        Extension(
            "rt_runtime.planning._verify",
            sources=["rt_runtime/planning/_verify.c"],
            extra_compile_args=FLAGS,
            libraries=["m"],
            optional=True,
        ),
        # The same kernel for CPUs with AVX2 (4 doubles per vector: plan ~23 % faster, the
        # same results bit for bit); verify.py picks it at run time where the CPU has AVX2. A
        # compiler without -mavx2 (another architecture) skips it.
        Extension(
            "rt_runtime.planning._verify_avx2",
            sources=["rt_runtime/planning/_verify.c"],
            extra_compile_args=[*FLAGS, "-mavx2"],
            define_macros=[("VK_AVX2", "1")],
            libraries=["m"],
            optional=True,
        ),
    ],
)
