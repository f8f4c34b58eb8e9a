"""Precompute the per-vertex visibility cubemaps of a scene (Inger et al., all-frequency relighting).

    python trainers/precompute_visibility.py bunny_relight --cubemap 64 --out out/bunny_vis.npz

The same as ``torch-brdf precompute-visibility`` (see ``--help``): finished chunks of vertices
are checkpointed next to the output (``out/bunny_vis.chunks/``), so an interrupted run (Ctrl-C)
continues where it stopped when run again with the same arguments; the record is written
atomically with a format version and a checksum (the maps as a base-128 varint stream).
Open it with ``VertexVisibility.load`` and render with ``TripleProductRenderer`` or
``torch-brdf relight``.
"""

from torch_brdf.cli import app

if __name__ == "__main__":
    app(["precompute-visibility", *__import__("sys").argv[1:]], prog_name="torch-brdf")
