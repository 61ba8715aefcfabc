"""A scene factory for examples/batch/jobs.jsonl: `{"scene": {"factory": "scenes:sphere_row",
"args": {"count": 5}}}` imports this module (the job file's folder is on sys.path) and calls the
function with the row's `args`; it returns a `jaxpbr.Scene`."""

import jaxpbr as jp


def sphere_row(count: int = 5, metallic: float = 1.0, spacing: float = 2.2) -> jp.Scene:
    """`count` unit spheres in a row, roughness rising from 0.05 to 1 left to right, on a ground
    plane, seen from the front. No environment: the job gives one."""
    spheres = [
        jp.Sphere(center=((k - (count - 1) / 2) * spacing, 1.0, 0.0), radius=1.0,
                  material=jp.Material(base_color=(0.9, 0.9, 0.9), metallic=metallic,
                                       roughness=0.05 + 0.95 * k / max(1, count - 1)))
        for k in range(count)
    ]
    ground = jp.Plane(point=(0.0, 0.0, 0.0), normal=(0.0, 1.0, 0.0),
                      material=jp.Material(base_color=(0.3, 0.3, 0.3), roughness=0.8))
    width = count * spacing
    camera = jp.Camera(position=(0.0, 2.0, 0.8 * width + 1.0), target=(0.0, 1.0, 0.0), fov_y_deg=40.0)
    return jp.Scene(camera=camera, objects=[*spheres, ground])
