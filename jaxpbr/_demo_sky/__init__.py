"""The demo's procedural sky at 128^2 faces, baked (data only).

A baked IBL set (ibl.json, per-face float32 EXR cubes, brdf_lut.exr, lights.json: the files of
`jaxpbr.write_baked`), written by `jaxpbr.rendering.demo.write_demo_sky` and read by
`jaxpbr.rendering.demo.shipped_demo_sky`, so that the demo's first render bakes nothing. A test
checks that a fresh bake of the sky equals it.
"""
