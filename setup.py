"""Builds jaxvisco's one C++ extension: the XLA foreign-function targets of the host
sparse LU (jaxvisco/_solver/_ffi/hostlu.cc). Everything else is in pyproject.toml.

The headers come from jaxlib (a build requirement); the extension links against
nothing but Python. It is optional: where it does not build, jaxvisco falls back to
`jax.pure_callback` (same results; JAX then does not cache the compiled programs).
"""

import importlib.util
import os
import sysconfig

from setuptools import Extension, setup


def _jaxlib_include():
    spec = importlib.util.find_spec("jaxlib")
    if spec is None or not spec.submodule_search_locations:
        return []
    return [os.path.join(spec.submodule_search_locations[0], "include")]


setup(
    ext_modules=[
        Extension(
            "jaxvisco._solver._ffi._hostlu",
            sources=["jaxvisco/_solver/_ffi/hostlu.cc"],
            include_dirs=_jaxlib_include() + [sysconfig.get_paths()["include"]],
            extra_compile_args=["-std=c++17", "-O2", "-Wno-attributes", "-Wno-return-type"],
            language="c++",
            optional=True,
        )
    ]
)
