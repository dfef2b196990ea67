"""Whether two checkouts render the shipped scenes bit for bit alike (issue 31: a restructuring keeps outputs).

Each checkout renders every scene file in its renderer/scenes/ (the gallery list left out) at 160×120, 2 spp,
seed 7, one process, with the default intersector and with `intersector="torch"`, in a fresh interpreter that
imports `renderer` from that checkout; the arrays are then compared exactly.

    python benchmarks/history/bit_identity.py OLD_CHECKOUT NEW_CHECKOUT
"""
from __future__ import annotations

import glob
import json
import os
import subprocess
import sys
import tempfile

RENDER = r"""
import glob, json, os, sys
import numpy as np
root, out = sys.argv[1], sys.argv[2]
sys.path.insert(0, root)
import renderer
assert renderer.__file__.startswith(root), renderer.__file__
for path in sorted(glob.glob(os.path.join(root, "renderer", "scenes", "*.json"))):
    with open(path) as f:
        if not isinstance(json.load(f), dict):
            continue
    scene = renderer.load_scene(path, ["image.width=160", "image.height=120"])
    name = os.path.basename(path)[:-5]
    for intersector in ("torch", None):
        kw = {} if intersector is None else {"intersector": intersector}
        img = renderer.render(scene, spp=2, seed=7, workers=1, **kw).image.numpy()
        np.save(os.path.join(out, f"{name}_{intersector or 'default'}.npy"), img)
"""


def render_all(checkout: str, out: str) -> None:
    subprocess.run([sys.executable, "-c", RENDER, os.path.abspath(checkout), out], check=True)


def main(argv=None) -> int:
    import numpy as np

    old, new = (argv or sys.argv[1:])[:2]
    with tempfile.TemporaryDirectory() as tmp:
        a, b = os.path.join(tmp, "old"), os.path.join(tmp, "new")
        os.makedirs(a), os.makedirs(b)
        render_all(old, a)
        render_all(new, b)
        differ = 0
        for f in sorted(glob.glob(os.path.join(a, "*.npy"))):
            other = os.path.join(b, os.path.basename(f))
            same = os.path.exists(other) and np.array_equal(np.load(f), np.load(other))
            differ += not same
            print(f"{os.path.basename(f)[:-4]}: {'identical' if same else 'DIFFERS'}")
    print(json.dumps({"differ": differ}))
    return 1 if differ else 0


if __name__ == "__main__":
    raise SystemExit(main())
