# Dr.Jit reads DRJIT_LIBLLVM_PATH when it is first imported: point it at the libLLVM the simulator
# would choose (a system libLLVM 17-19, else the karellen-llvm-core wheel) before any test module
# here imports mitsuba directly, so the tests see the same renderer as 'hybridhdr simulate'.
try:
    from hybridhdr.simulate.render import _prepare_llvm_env
except ImportError:  # pragma: no cover - the simulate extra's modules are missing
    pass
else:
    _prepare_llvm_env()
