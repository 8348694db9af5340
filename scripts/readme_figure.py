"""The README's picture: a real mesh before and after `jaxci.smooth`, its surface coloured by element condition
and its worst elements marked (`jaxci.experiments.smooth_report.surface_figure`).

    python scripts/readme_figure.py [--mesh ../shared/data/mesquite/pave3.e.vtk] [--out docs/smoothing.png]

The default mesh is Mesquite's pave3 (1,791 hexahedra, 106 of them inverted), from the repository's sibling folder
``shared/data``. The output is refused if it exists (``--force`` replaces it).
"""

from __future__ import annotations

import argparse
import io
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh", default=str(ROOT.parent / "shared" / "data" / "mesquite" / "pave3.e.vtk"))
    ap.add_argument("--out", default=str(ROOT / "docs" / "smoothing.png"))
    ap.add_argument("--dpi", type=int, default=80)
    ap.add_argument("--force", action="store_true")
    args = ap.parse_args(argv)
    out = Path(args.out)
    if out.exists() and not args.force:
        print(f"{out}: exists; pass --force to replace it", file=sys.stderr)
        return 2

    import jaxci
    from jaxci.experiments.plots import pyplot
    from jaxci.experiments.smooth_report import surface_figure, worst_elements

    def _num(v):
        return "inverted" if v == float("inf") else f"{v:.4g}"

    mesh = jaxci.read_mesh(args.mesh)
    res = jaxci.smooth(mesh)
    worst = worst_elements(mesh, mesh.points, res.mesh.points)
    b, a = res.before, res.after
    title = (f"{Path(args.mesh).name}: {b.n_elements} hexahedra, {b.inverted_elements} inverted -> "
             f"{a.inverted_elements}; worst element kappa/3 {_num(worst[0][0].before)} -> {_num(a.max_condition)}; "
             f"jaxci smooth (default), {res.wall_time:.1f} s")
    fig = surface_figure(mesh, mesh.points, res.mesh.points, worst, title)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=args.dpi, metadata={"Software": None})
    pyplot().close(fig)
    out.write_bytes(buf.getvalue())
    print(f"wrote {out} ({len(buf.getvalue()) // 1024} kB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
