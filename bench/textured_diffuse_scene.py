"""A textured *Lambertian* scene for the albedo flatness prior's risk check.

The benchmark scenes that drop the specular lobe (sphere_diffuse) have a constant albedo, so
they cannot show whether ``LossConfig.w_albedo_flat`` (on once the lobe is off) flattens a real
texture. This writes a torus with the project's 3D checker albedo (two colours of luminance
0.42 and 0.52, cell 0.4 object units), Lambertian, one point light, in the layout that
``python -m bench run --scenes-root ROOT --scenes checker_lambert`` reads
(``ROOT/checker_lambert/input/dtu``, ``gt/...``)::

    python -m bench.textured_diffuse_scene /tmp/synth_scenes
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from nepf_core.data import synth_shapes
from nepf_core.data.synth import make_scene

NAME = "checker_lambert"


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("root", help="scenes root to write ROOT/checker_lambert into")
    p.add_argument("--resolution", type=int, default=128)
    a = p.parse_args(argv)
    out = Path(a.root) / NAME
    synth_shapes.MATERIALS.setdefault("checker_lambert", {"albedo": "checker", "roughness": 1.0, "metallic": 0.0,
                                                           "lambertian": True, "specular": False})
    make_scene(out, shape="torus", material="checker_lambert", n_views=32, n_test=8, resolution=a.resolution,
               light_position=(2.5, -3.0, 4.0), light_intensity=70.0, camera_distance=3.0, name=NAME)
    (out / "input").mkdir(exist_ok=True)
    link = out / "input" / "dtu"
    if not link.exists():
        os.symlink("../dtu", link)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
