"""The nonlinear estimator's optional compiled solve, built at install: ftsensord/model/_nlsolve.c
and _nlmodel.c (plain C, no Python headers), called through ctypes by ftsensord/model/nlcompiled.py. Where no
C compiler is found the install goes on without it and the estimator runs numpy's solve, the
same fit. Everything else about the package is in pyproject.toml."""

from setuptools import Extension, setup

# optional: a failed compile warns and the install goes on (the numpy solve stays).
setup(ext_modules=[Extension("ftsensord.model._nlsolve", ["ftsensord/model/_nlsolve.c", "ftsensord/model/_nlmodel.c"],
                             depends=["ftsensord/model/_nlsolve.h"], optional=True, extra_compile_args=["-std=c99"],
                             libraries=["m"])])
