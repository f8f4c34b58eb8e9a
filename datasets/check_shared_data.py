"""Check the shared data folder with torch_brdf's own readers and print a summary.

    python datasets/check_shared_data.py            # the data folder: $TORCH_BRDF_DATA, else the cache's

Reads every env map (EXR: finite, non-negative, lat-long 2:1) and mesh (valid triangles)
and prints one line per file, then one JSON object. Exit code 1 if anything fails to
load, 2 if the folder is missing. The data itself is never copied into the repository.
"""

from __future__ import annotations

import json
import sys
import warnings

from torch_brdf.data import data_root
from torch_brdf.errors import TorchBRDFError
from torch_brdf.scene import EnvironmentMap, load_mesh


def main() -> int:
    root = data_root()
    if root is None:
        print("shared data folder not found (set TORCH_BRDF_DATA)", file=sys.stderr)
        return 2
    report, failed = {}, 0
    for path in sorted((root / "envmaps").glob("*.exr")):
        try:
            env = EnvironmentMap.from_exr(path)
            h, w = env.radiance.shape[:2]
            report[path.name] = {"size": [w, h], "integral_rgb": [round(float(x), 4) for x in env.integral()]}
        except TorchBRDFError as exc:
            failed += 1
            report[path.name] = {"error": str(exc)}
        print(path.name, report[path.name])
    for path in sorted((root / "meshes").rglob("*.obj")) + sorted((root / "meshes").glob("*.ply")):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                m = load_mesh(path)
                report[path.name] = {"triangles": len(m.faces), "warnings": [str(c.message) for c in caught]}
            except TorchBRDFError as exc:
                failed += 1
                report[path.name] = {"error": str(exc)}
        print(path.relative_to(root), report[path.name])
    print(json.dumps({"root": str(root), "files": len(report), "failed": failed}))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
