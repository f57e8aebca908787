"""numpy reference implementations the compiled kernels are tested against (test-only)."""
