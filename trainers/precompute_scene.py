"""Precompute the multibounce polynomial tensors of a scene (Ben-Artzi et al. 2008).

    python trainers/precompute_scene.py cornell_box_glossy --series 64,1,1,1 --spp 64 --out out/cb.npz

The same as ``torch-brdf precompute`` (see ``--help``): tiles are checkpointed next to the
output (``OUT.tiles/``), so an interrupted run (Ctrl-C) continues where it stopped when run
again with the same arguments; the output is written atomically with a format version and a
checksum. Open it with ``PolynomialTensors.load`` and render with ``PolynomialRenderer``.
"""

from torch_brdf.cli import app

if __name__ == "__main__":
    app(["precompute", *__import__("sys").argv[1:]], prog_name="torch-brdf")
