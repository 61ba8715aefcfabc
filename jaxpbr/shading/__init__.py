"""Shading kernels: the material, BRDF terms and models, the glTF extensions' layered BSDF, punctual
and disc lights, sampling, and the albedo tables (split-sum and sheen LUTs) the kernels read."""
