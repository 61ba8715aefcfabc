"""Image-based lighting: cube maps and environments, their precompute (irradiance, GGX- and
Charlie-prefiltered mips), sun extraction, split-sum shading, the float64 references and the
error of every precompute, environment files in and cube maps out."""
