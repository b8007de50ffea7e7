"""``implantplan phantom [CASE] --out DIR``: a synthetic CBCT of a mesh case (DESIGN.md section 12).

Writes ``DIR/ct/CT0001.dcm ...`` (a DICOM CT series of the case's scan: air, soft tissue, bone,
teeth, a canal under each site, noise; systems.anatomy.phantom), ``DIR/canals.yaml`` (the canal
polylines, mm, in the patient frame = the case's mesh frame as scanned) and ``DIR/case.yaml``
(the case with ``mesh.path: ct`` and ``anatomy: {canals_file: canals.yaml}``: ``implantplan plan
DIR/case.yaml`` plans the phantom and checks the clinical distances). The
folder is built beside ``DIR`` and moved in at the end; an existing ``DIR`` is replaced only
when the project made it (analyses.out_folder's marker) or with ``--force``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from implantplan.analyses import out_folder
from implantplan.analyses.case import default_case_path, load_case
from implantplan.analyses.pipeline import planned_implants
from implantplan.systems.anatomy.cbct import is_volume_path
from implantplan.systems.anatomy.dicom_ct import SeriesIds, write_ct_series
from implantplan.systems.anatomy.phantom import PhantomSpec, make_phantom
from implantplan.systems.errors import InputError
from implantplan.systems.files import read_yaml, write_text_atomic
from implantplan.systems.fpsm.oral_mesh import center_frame, load_oral_mesh

VOXEL_MM = (0.2, 2.0)


def register(subparsers) -> None:
    p = subparsers.add_parser("phantom", help="a synthetic CBCT (DICOM CT series) of a mesh case")
    p.add_argument("case", nargs="?", type=Path, default=None, metavar="CASE",
                   help="case YAML with a mesh scan (default: the bundled default case)")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--voxel-mm", type=float, default=0.4,
                   help="voxel size (mm; 0.2-0.4 is a clinical CBCT's, coarser for tests)")
    p.add_argument("--noise-hu", type=float, default=20.0, help="Gaussian noise sigma (HU)")
    p.add_argument("--seed", type=int, default=None, help="noise seed (default: the case's)")
    p.add_argument("--force", action="store_true",
                   help="replace an --out folder that is not a phantom folder")
    p.set_defaults(func=_cmd)


def make_phantom_folder(case_file: Path, out: Path, *, voxel_mm: float, noise_hu: float,
                        seed: int | None, force: bool) -> dict:
    """Write the phantom of ``case_file`` into ``out`` (see the module docstring)."""
    if not VOXEL_MM[0] <= voxel_mm <= VOXEL_MM[1]:
        raise InputError("--voxel-mm", f"expected {VOXEL_MM[0]} to {VOXEL_MM[1]} mm, got "
                         f"{voxel_mm:g}")
    if not 0.0 <= noise_hu <= 500.0:
        raise InputError("--noise-hu", f"expected 0 to 500 HU, got {noise_hu:g}")
    out = out_folder.check_out(out, force=force)
    case = load_case(case_file)
    if is_volume_path(case.mesh.path):
        raise InputError("mesh.path", f"{case.mesh.path} is already a CBCT; expected a mesh case")
    scanned = load_oral_mesh(case.mesh.path, units=case.mesh.units, field="mesh.path")
    spec = PhantomSpec(voxel=voxel_mm * 1e-3, noise_hu=noise_hu)
    seed = case.seed if seed is None else seed
    if seed < 0:
        raise InputError("--seed", f"expected a number >= 0, got {seed}")
    X_WC = center_frame(case.center.origin, case.center.z_axis, x_hint=case.center.x_hint)
    phantom = make_phantom(scanned, spec, seed=seed, close_cuts=case.mesh.close_open_cuts,
                           implants=planned_implants(case, X_WC, scanned=True),
                           implant_radii=[s.implant_diameter / 2 for s in case.sites])
    with out_folder.staged(out, "phantom") as staging:
        files = write_ct_series(staging / "ct", phantom.hu, phantom.origin * 1e3,
                                [voxel_mm] * 3, ids=SeriesIds(patient_id=f"PHANTOM-{case.name}"))
        canals = {"schema_version": 1, "frame": "DICOM patient frame (LPS, mm) = the case's "
                  "mesh frame as scanned", "radius_mm": phantom.canal_radius * 1e3,
                  "canals": [{"site": s.name, "polyline_mm": np.round(c * 1e3, 4).tolist()}
                             for s, c in zip(case.sites, phantom.canals, strict=True)]}
        write_text_atomic(staging / "canals.yaml", yaml.safe_dump(canals, sort_keys=False))
        data = read_yaml(case_file, field="case")
        data["mesh"]["path"] = "ct"
        data["anatomy"] = {**(data.get("anatomy") or {}), "canals_file": "canals.yaml"}
        data["name"] = f"{case.name}-cbct"
        header = (f"# implantplan phantom of {case_file}: mesh.path is its synthetic CBCT "
                  f"({voxel_mm:g} mm voxels); the frames are DICOM's patient frame (LPS, mm).\n")
        write_text_atomic(staging / "case.yaml", header + yaml.safe_dump(data, sort_keys=False))
    return {"slices": len(files), "shape_kji": list(phantom.hu.shape), "voxel_mm": voxel_mm,
            "canals": len(phantom.canals)}


def _cmd(args) -> int:
    case_file = args.case if args.case is not None else default_case_path()
    info = make_phantom_folder(case_file, args.out, voxel_mm=args.voxel_mm,
                               noise_hu=args.noise_hu, seed=args.seed, force=args.force)
    k, j, i = info["shape_kji"]
    print(f"phantom: {args.out / 'ct'} ({info['slices']} slices, {i} x {j} x {k} voxels of "
          f"{info['voxel_mm']:g} mm, {info['canals']} canals)")
    print(f"case: {args.out / 'case.yaml'}")
    return 0
