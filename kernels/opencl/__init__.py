"""OpenCL backend (pyopencl): PoCL on the CPU by default, any OpenCL device on request."""
