"""`jaxci generate box --n 9 --amplitude 0.3 --seed 0 out.vtu [--force]`: structured and perturbed box meshes.

An existing OUT is refused without ``--force`` (`_files.check_output`); the file is written atomically.
"""

from __future__ import annotations


def add_args(p) -> None:
    p.add_argument("kind", choices=["box", "cube27", "cube64", "cube729"],
                   help="'box' (sizes from --n/--nx/--ny/--nz) or one of the paper's cubes")
    p.add_argument("out", help="output mesh file")
    p.add_argument("--n", type=int, default=3, help="elements per axis (default 3)")
    p.add_argument("--nx", type=int, help="elements along x (default --n)")
    p.add_argument("--ny", type=int, help="elements along y (default --n)")
    p.add_argument("--nz", type=int, help="elements along z (default --n)")
    p.add_argument("--size", type=float, nargs=3, default=(1.0, 1.0, 1.0), metavar=("LX", "LY", "LZ"))
    p.add_argument("--amplitude", type=float, default=0.0, help="perturbation, fraction of the spacing")
    p.add_argument("--which", choices=["sliding", "interior"], default="sliding",
                   help="perturb boundary nodes along the boundary too (sliding) or interior nodes only")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--force", action="store_true", help="overwrite OUT if it is an existing file")


def run(args) -> int:
    from ..mesh.generate import paper_case, perturb_box
    from ._files import check_output

    out = check_output(args.out, force=args.force)
    if args.kind == "box":
        nx, ny, nz = (args.n if v is None else v for v in (args.nx, args.ny, args.nz))
        mesh = perturb_box(nx, ny, nz, amplitude=args.amplitude, seed=args.seed,
                           which=args.which, size=tuple(args.size))
    else:
        mesh = paper_case(args.kind, seed=args.seed)
    out.write(mesh)
    print(f"wrote {args.out}: {mesh.n_nodes} nodes, {mesh.n_hexes} hexahedra")
    return 0
