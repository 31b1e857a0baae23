"""Tet mesh of two touching boxes (breast in front of muscle): volume, conforming interface,
regions, named sets, quality; plus the exporters on the same mesh."""

import xml.etree.ElementTree as ET

import meshio
import numpy as np
import pytest

from breastmodel.febio import write_mesh_feb
from mechanics.mesh import REGIONS
from meshing import mesh_labels
from meshing.analytic import touching_boxes_labels
from meshing.export import write_ply, write_vtu
from meshing.labels import tissue_masks
from meshing.quality import report
from meshing.sets import tet_faces
from meshing.surface import enclosed_volume, tissue_surface, triangle_areas, triangle_normals

SIZE = (60.0, 40.0, 50.0)  # x, y, z mm; breast is the anterior (small y) 20 mm
SPLIT = 20.0
H = 5.0  # element size, mm


@pytest.fixture(scope="module")
def boxes():
    labels = touching_boxes_labels(size=SIZE, split_y=SPLIT, spacing=1.0)
    return labels, mesh_labels(labels, size_mm=H)


@pytest.fixture(scope="module")
def boxes_uniform():
    """Uniform element size (no grading): the interface embedding at a known size."""
    labels = touching_boxes_labels(size=SIZE, split_y=SPLIT, spacing=1.0)
    return labels, mesh_labels(labels, size_mm=H, coarse=1.0)


def test_tet_volume_matches_the_enclosed_surface_volume(boxes):
    labels, mesh = boxes
    masks = tissue_masks(labels)
    v, f = tissue_surface(masks.union, masks.grid, target_edge_mm=0.75 * H)
    vol = mesh.signed_volumes()
    assert (vol > 0).all()
    # Issue target 0.5 %: fTetWild keeps the boundary within 0.1 H of the surface.
    assert vol.sum() == pytest.approx(enclosed_volume(v, f), rel=0.005)
    breast = np.isin(mesh.region, [REGIONS["breast_left"], REGIONS["breast_right"]])
    # The breast box holds SPLIT / SIZE[1] of the volume; its smoothed edges lose a little.
    assert vol[breast].sum() == pytest.approx(SIZE[0] * SPLIT * SIZE[2], rel=0.03)


def test_interface_is_shared_flat_and_oriented_from_muscle_to_breast(boxes_uniform):
    _, mesh = boxes_uniform
    iface = mesh.face_sets["interface"]
    # every interface face is a face of exactly one breast tet and one muscle tet
    bf, bo, sf, so = tet_faces(mesh.tets)
    key = {tuple(sorted(t)): k for k, t in enumerate(sf)}
    idx = np.array([key[tuple(sorted(t))] for t in iface])
    kinds = np.sort(np.isin(mesh.region[so[idx]], [1, 3]).astype(int), axis=1)
    assert (kinds == [0, 1]).all()
    # no interface face on the outer boundary
    bkeys = {tuple(sorted(t)) for t in bf}
    assert not any(tuple(sorted(t)) in bkeys for t in iface)
    # the patch is the 60 x 50 plane y = -SIZE[1]/2 + SPLIT, normal -y (muscle is behind)
    x = mesh.nodes
    y0 = -SIZE[1] / 2 + SPLIT
    n = triangle_normals(x, iface)
    area = triangle_areas(x, iface)
    # Away from the rim (two elements in from the box's sides) the patch is that plane: over
    # 18 fTetWild runs, node deviation <= 0.04 mm (one element in: up to 1.27 mm, the rim's
    # staircase reaches that far in; an earlier bound there was flaky). The improvement
    # pass may move an interface node off the plane to mend a flat tet (meshing.volume.
    # _improve_once, by a fraction of an element): one CI run had one such node at 1.07 mm.
    c, lo, hi = x[iface].mean(axis=1), x.min(axis=0), x.max(axis=0)
    inner = ((c[:, 0] > lo[0] + 2 * H) & (c[:, 0] < hi[0] - 2 * H)
             & (c[:, 2] > lo[2] + 2 * H) & (c[:, 2] < hi[2] - 2 * H))
    dev = np.abs(x[np.unique(iface[inner]), 1] - y0)
    assert np.median(dev) < 0.01 * H and np.sum(dev > 0.1 * H) <= 2
    assert dev.max() < 0.5 * H
    assert (area[inner] * n[inner, 1]).sum() / area[inner].sum() < -0.999
    assert area[inner].sum() == pytest.approx((SIZE[0] - 4 * H) * (SIZE[2] - 4 * H), rel=0.1)
    # The rim is a staircase of about one element where the interface meets the skin (the
    # embedded patch stops short of the outer surface): there it deviated up to 5.3 mm, and
    # the whole patch's area exceeded the plane's by 6-10 % (a 2-element rim of 5 mm steps).
    dev_all = np.abs(x[np.unique(iface), 1] - y0)
    assert dev_all.max() < 1.5 * H
    assert (area * n[:, 1]).sum() / area.sum() < -0.85
    assert area.sum() == pytest.approx(SIZE[0] * SIZE[2], rel=0.15)


def test_skin_and_fixed_sets(boxes):
    _, mesh = boxes
    x = mesh.nodes
    skin = mesh.face_sets["skin"]
    n, c = triangle_normals(x, skin), x[skin].mean(1)
    # outward: away from the breast tet each face bounds (every one); mostly away from the
    # box centre too (the rim's staircase has faces in concave corners: up to 1 % of them
    # over 11 runs); and on the breast box: the interface patch stops gap = max(1.5 voxel,
    # 0.2 H) = 1.5 mm short of the skin (meshing.volume), so in that rim band tets are split by
    # centroid, not along the plane, and skin faces may cross it by up to the gap plus the
    # envelope (0.1 H); measured in 6 meshings: centroids up to 0.69 mm past the plane, at most
    # one face (<= 0.17 % of the skin area)
    bf, owner, _, _ = tet_faces(mesh.tets)
    tet_of = {tuple(sorted(f)): t for f, t in zip(bf.tolist(), owner.tolist(), strict=True)}
    inside = x[mesh.tets[[tet_of[tuple(sorted(f))] for f in skin.tolist()]]].mean(axis=1)
    assert (np.einsum("ij,ij->i", n, c - inside) > 0).all()
    assert (np.einsum("ij,ij->i", n, c) > 0).mean() > 0.98
    plane = -SIZE[1] / 2 + SPLIT
    assert c[:, 1].max() < plane + 1.5 + 0.1 * H
    beyond = c[:, 1] > plane + 0.1 * H
    assert triangle_areas(x, skin[beyond]).sum() < 0.01 * triangle_areas(x, skin).sum()
    # the front (anterior) face is 60 x 50 mm less the rounded rim (normal tilted > 25 deg),
    # about a 1 mm strip along its 220 mm perimeter at this element size
    front = n[:, 1] < -0.9
    assert triangle_areas(x, skin[front]).sum() == pytest.approx(SIZE[0] * SIZE[2], rel=0.09)
    # fixed: posterior face of the muscle box (y = +20)
    fixed = mesh.node_sets["fixed"]
    # (the rounded back edges, normals tilted < 60 deg from +y, count as posterior too)
    assert len(fixed) > 20 and np.mean(np.abs(x[fixed, 1] - SIZE[1] / 2) < 1.5) > 0.8
    assert x[fixed, 1].min() > 0.0
    # end bands at the top and bottom of the skin, disjoint
    sup, inf = mesh.node_sets["skin_superior"], mesh.node_sets["skin_inferior"]
    assert x[sup, 2].min() > x[inf, 2].max()
    assert set(sup) <= set(mesh.node_sets["skin"])
    assert set(mesh.node_sets["fascia_superior"]) <= set(mesh.node_sets["interface"])


def test_left_right_split_and_ligament_pairs(boxes):
    _, mesh = boxes
    cent = mesh.nodes[mesh.tets].mean(1)
    left = mesh.region == REGIONS["breast_left"]
    right = mesh.region == REGIONS["breast_right"]
    assert left.any() and right.any()
    assert cent[left, 0].min() > cent[right, 0].max() - 5.0  # left = larger x
    in_breast = np.zeros(mesh.n_nodes, bool)
    in_breast[mesh.tets[left | right].ravel()] = True
    in_muscle = np.zeros(mesh.n_nodes, bool)
    in_muscle[mesh.tets[mesh.region == REGIONS["muscle"]].ravel()] = True
    for name in ("ligament_inframammary", "ligament_medial", "ligament_lateral"):
        p = mesh.node_pairs[name]
        assert p.ndim == 2 and p.shape[1] == 2 and len(p) > 0, name
        assert in_breast[p[:, 0]].all() and in_muscle[p[:, 1]].all()
        assert not in_breast[p[:, 1]].any()
        d = np.linalg.norm(mesh.nodes[p[:, 0]] - mesh.nodes[p[:, 1]], axis=1)
        assert (d > 0.5).all() and (d < 3 * H).all()
    # the inframammary anchors sit lower than the medial/lateral ones on average
    z = lambda k: mesh.nodes[mesh.node_pairs[k][:, 0], 2].mean()  # noqa: E731
    assert z("ligament_inframammary") < z("ligament_medial")


def test_quality_report(boxes):
    _, mesh = boxes
    q = report(mesh)
    assert q["n_tets"] == mesh.n_tets and q["n_inverted"] == 0
    assert sum(r["tets"] for r in q["regions"].values()) == mesh.n_tets
    assert 1.0 <= q["aspect_ratio"]["min"] and q["aspect_ratio"]["median"] < 3.0
    assert 0.0 <= q["skewness"]["min"] and q["skewness"]["median"] < 0.5
    assert q["min_dihedral_deg"]["min"] > 0.0


def test_exports_round_trip(boxes, tmp_path):
    _, mesh = boxes
    m = meshio.read(write_vtu(tmp_path / "m.vtu", mesh))
    assert np.allclose(m.points, mesh.nodes)
    assert np.array_equal(m.cells_dict["tetra"], mesh.tets)
    assert np.array_equal(m.cell_data["region"][0], mesh.region)
    assert m.point_data["fixed"].sum() == len(mesh.node_sets["fixed"])

    root = ET.parse(write_mesh_feb(mesh, tmp_path / "m.feb")).getroot()
    assert root.tag == "febio_spec" and root.get("version") == "4.0"
    assert len(root.findall("./Mesh/Nodes/node")) == mesh.n_nodes
    elems = root.findall("./Mesh/Elements")
    assert sum(len(e) for e in elems) == mesh.n_tets
    ids = sorted(int(el.get("id")) for e in elems for el in e)
    assert ids == list(range(1, mesh.n_tets + 1))
    skin = root.find("./Mesh/Surface[@name='skin']")
    assert len(skin) == len(mesh.face_sets["skin"])
    first = [int(s) - 1 for s in skin[0].text.split(",")]
    assert first == mesh.face_sets["skin"][0].tolist()
    fixed = root.find("./Mesh/NodeSet[@name='fixed']").text.split(",")
    assert len(fixed) == len(mesh.node_sets["fixed"])
    assert {d.get("name") for d in root.findall("./MeshDomains/SolidDomain")} == {
        "breast_left", "breast_right", "muscle"}

    v = mesh.nodes
    p = meshio.read(write_ply(v, mesh.face_sets["skin"], tmp_path / "s.ply"))
    assert np.allclose(p.points, v) and np.array_equal(
        p.cells_dict["triangle"], mesh.face_sets["skin"])


def test_tissue_fragments_go_to_the_other_tissue():
    """A muscle tet touching only breast tets, and a breast tet touching only muscle, are
    fragments (held by contact alone once the interface is split): each takes the other
    tissue's region; the two bodies keep theirs."""
    from zoo import box

    from meshing.volume import _absorb_fragments

    mesh = box(shape=(8, 8, 4), size=(8.0, 8.0, 4.0))
    z = mesh.nodes[mesh.tets].mean(axis=1)[:, 2]
    region = np.where(z < 2.0, REGIONS["muscle"], REGIONS["breast_left"]).astype(np.int32)
    top = np.flatnonzero(z > 3.0)[0]  # a tet in the top layer: only breast around it
    bottom = np.flatnonzero(z < 1.0)[0]  # a tet in the bottom layer: only muscle around it
    region[top], region[bottom] = REGIONS["muscle"], REGIONS["breast_left"]
    out = _absorb_fragments(mesh.tets, region)
    assert out[top] == REGIONS["breast_left"] and out[bottom] == REGIONS["muscle"]
    changed = np.flatnonzero(out != region)
    assert sorted(changed) == sorted([top, bottom])


def test_tets_hanging_by_an_edge_or_a_vertex_are_not_the_main_body():
    """A tet that meets the mesh at an edge, or at a vertex, can rotate about it; only the
    face-connected body is kept (its tets are held rigidly by shared faces)."""
    from zoo import box

    from meshing.volume import _main_body

    mesh = box(shape=(4, 4, 2), size=(4.0, 4.0, 2.0))
    nodes, tets = mesh.nodes, mesh.tets
    corner = int(np.argmax(nodes.sum(axis=1)))  # (4, 4, 2)
    edge_mate = int(np.flatnonzero(np.all(nodes == [3.0, 4.0, 2.0], axis=1))[0])
    n = len(nodes)
    nodes = np.vstack([nodes, [[4.5, 4.5, 3.0], [3.5, 4.5, 3.5], [6.0, 6.0, 6.0],
                               [7.0, 6.0, 6.0], [6.0, 7.0, 6.0]]])
    on_edge = [corner, edge_mate, n, n + 1]
    on_vertex = [corner, n + 2, n + 3, n + 4]
    tets = np.vstack([tets, on_edge, on_vertex])
    body = _main_body(tets)
    assert np.flatnonzero(~body).tolist() == [len(tets) - 2, len(tets) - 1]


def test_mesh_made_in_a_worker_process_matches_the_one_made_here(boxes, tmp_path, monkeypatch):
    """The pipeline meshes an adult reference in a ``python -m meshing.background`` worker
    beside its other stages: the mesh of the same label map, at the size asked, with every
    set; a worker's error is raised when the result is taken; leaving the context stops a
    worker still running.

    Not bit for bit: pymeshlab's isotropic remeshing gives another surface now and then on
    the same input in a fresh process (this label map's union: 5 of 407 runs, with one OpenMP
    thread and with address randomisation off too; README, "`breastmodel mesh` /
    `surface`"), and that surface's tet mesh has 1211 nodes against 1131, its volume the same
    to 0.003 %, its breast's and muscle's to 0.25 %, each side's to 1.3 %. The bounds below
    hold both and would catch a mesh of another map, size or grading."""
    from pathlib import Path

    import SimpleITK as sitk

    from meshing import surface
    from meshing.background import mesh_in_background

    labels, here = boxes
    path = tmp_path / "labels.nii.gz"
    sitk.WriteImage(labels, str(path))
    monkeypatch.setattr(surface, "PARALLEL_VOXELS", 0)
    with mesh_in_background(path, size_mm=H) as job:
        assert job.proc is not None  # the worker, not this process
        mesh, size, why = job.result()
    assert (size, why) == (H, "given")
    for kind in ("node_sets", "face_sets", "node_pairs"):
        assert getattr(mesh, kind).keys() == getattr(here, kind).keys()
    assert abs(mesh.n_nodes / here.n_nodes - 1) < 0.1
    assert set(np.unique(mesh.region)) == set(np.unique(here.region))
    vol, vol_here = mesh.signed_volumes(), here.signed_volumes()
    assert (vol > 0).all()
    assert vol.sum() == pytest.approx(vol_here.sum(), rel=1e-3)
    breast = [REGIONS["breast_left"], REGIONS["breast_right"]]
    for codes, rel in ((breast, 0.01), ([REGIONS["muscle"]], 0.01),
                       # a side's tets are those whose centroid lies on its side of the
                       # midline: the other surface's mesh moved 1.3 % across it
                       ([REGIONS["breast_left"]], 0.03), ([REGIONS["breast_right"]], 0.03)):
        assert vol[np.isin(mesh.region, codes)].sum() == pytest.approx(
            vol_here[np.isin(here.region, codes)].sum(), rel=rel)
    empty = sitk.GetImageFromArray(np.zeros(sitk.GetArrayViewFromImage(labels).shape, np.uint8))
    empty.CopyInformation(labels)
    sitk.WriteImage(empty, str(tmp_path / "empty.nii.gz"))
    with mesh_in_background(tmp_path / "empty.nii.gz", size_mm=H) as job:
        with pytest.raises(ValueError, match="breast"):
            job.result()
    with mesh_in_background(path, size_mm=H) as job:
        proc, folder = job.proc, job.tmp.name
    assert proc.poll() is not None  # stopped (or finished) with the context
    assert not Path(folder).exists()
