"""``breastmodel mesh`` and ``breastmodel surface`` end to end on a small label map."""

import json

import meshio
import numpy as np
import SimpleITK as sitk

from breastmodel.cli import main
from meshing.analytic import touching_boxes_labels


def test_mesh_and_surface_commands(tmp_path):
    labels = tmp_path / "labels.nii.gz"
    sitk.WriteImage(touching_boxes_labels(size=(50.0, 30.0, 40.0), split_y=14.0, spacing=1.5),
                    str(labels))
    out = tmp_path / "mesh"
    assert main(["mesh", str(labels), "--out", str(out), "--size", "6"]) == 0
    for name in ("mesh.vtu", "mesh.feb", "mesh.npz", "skin.ply", "quality.json"):
        assert (out / name).stat().st_size > 0, name
    q = json.loads((out / "quality.json").read_text())
    m = meshio.read(out / "mesh.vtu")
    assert q["n_tets"] == len(m.cells_dict["tetra"]) > 100
    assert set(np.unique(m.cell_data["region"][0])) == {1, 2, 3}
    assert q["n_inverted"] == 0
    # the tet volume is the 50 x 30 x 40 box within the smoothing of its edges
    assert abs(q["volume_mm3"] / 60000.0 - 1) < 0.04

    ply = tmp_path / "skin.ply"
    assert main(["surface", str(labels), "--out", str(ply), "--edge", "2"]) == 0
    s = meshio.read(ply)
    assert len(s.cells_dict["triangle"]) > 100
    assert s.points[:, 1].max() < -15.0 + 14.0 + 1.0  # only the breast part (y < -1)


def test_bad_label_map_gives_one_error_line(tmp_path, capsys):
    arr = np.zeros((10, 10, 10), np.uint8)
    arr[2:5, 2:5, 2:5] = 9
    path = tmp_path / "bad.nii.gz"
    sitk.WriteImage(sitk.GetImageFromArray(arr), str(path))
    assert main(["mesh", str(path), "--out", str(tmp_path / "o")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("error: mesh [") and "unexpected label values 9" in err[-1]
    assert main(["surface", str(tmp_path / "missing.nii.gz"), "--out", "x.ply"]) == 1
