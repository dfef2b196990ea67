"""From samples to pixels: the render loop (`render`), samplers (`sampling`), recursive tracing
(`integrator`), the direct-light fast path (`direct`) the compiled Embree path (`fused`) and renders spread over a Ray
cluster (`distributed`)."""
