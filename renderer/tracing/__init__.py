"""From samples to pixels: the render loop (`render`), samplers (`sampling`), recursive tracing
(`integrator`), the direct-light fast path (`direct`), direct light as Dr.Jit kernels beside Embree (`jit_direct`,
the default where it applies), the compiled Embree path (`fused`) and renders spread over a Ray cluster
(`distributed`)."""
