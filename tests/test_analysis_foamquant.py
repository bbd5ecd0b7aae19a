"""The FoamQuant voxel route of ``python -m bubsub.bench analysis`` against an analytic foam (needs foamquant).

The benchmark's side-by-side table rests on :func:`bubsub.bench.analysis.foamquant_route`
reading FoamQuant's ``BubbleSegmentation`` and ``RegionProp`` correctly (voxel
indices to mm, the semi-axes' order, the contact reach). Here the route runs on
the exact voxelisation of ellipsoids, whose truth is analytic, and bubsub's
contacts from the meshes are set beside its voxel contacts. Skipped unless
foamquant is installed (``pip install --no-deps foamquant`` is enough).
"""

import numpy as np
import pytest

pytest.importorskip("foamquant")

from bubsub.bench.analysis import _match, foamquant_route  # noqa: E402
from bubsub.bench.analysis_truth import subdivided_ellipsoid  # noqa: E402
from bubsub.core.analysis.contacts import find_contacts  # noqa: E402
from bubsub.core.foam.ellipsoids import ellipsoid_labels  # noqa: E402
from test_analysis_contacts import small_foam, true_gap  # noqa: E402

VOXEL, GAP = 0.04, 0.06


def test_foamquant_route_on_voxelised_ellipsoids_and_contacts_beside_bubsub():
    foam = small_foam(7)
    centre = np.array([f[0] for f in foam])
    axes = np.array([f[1] for f in foam])
    rot = np.array([f[2] for f in foam])
    volume = 4 / 3 * np.pi * axes.prod(axis=1)
    lo = centre.min(axis=0) - 0.6
    n = np.ceil((centre.max(axis=0) + 0.6 - lo) / VOXEL).astype(int)
    hi = lo + n * VOXEL
    shape, extent = (n[2], n[1], n[0]), (lo[0], hi[0], lo[1], hi[1], lo[2], hi[2])
    binary = (ellipsoid_labels(centre, axes, rot, shape, extent) > 0).astype(np.uint8)
    m = foamquant_route(binary, extent, VOXEL, min_distance=4, gap=GAP, mask=np.ones(shape, bool))

    # every bubble found once, at its centre in mm (a voxel index read the wrong way round is millimetres off)
    match = _match(m["centroid"], {"centre": centre, "radius": np.cbrt(3 * volume / (4 * np.pi))})
    assert len(m["centroid"]) == len(match) == len(foam)
    i, t = np.array(list(match)), np.array(list(match.values()))
    assert np.abs(m["centroid"][i] - centre[t]).max() < 0.1 * VOXEL
    assert np.abs(m["volume"][i] / volume[t] - 1).max() < 0.02
    assert np.abs(m["axes"][i] / -np.sort(-axes[t], axis=1) - 1).max() < 0.02  # descending, as bubsub's
    assert not m["cut"].any()  # no label reaches the top or bottom slice

    truth = {(a, b) for a in range(len(foam)) for b in range(a + 1, len(foam))
             if np.linalg.norm(centre[a] - centre[b]) < 1.2 and true_gap(centre[a], foam[a][3], centre[b], foam[b][3]) < GAP}
    voxel_pairs = {tuple(sorted((int(t[list(i).index(a)]), int(t[list(i).index(b)])))) for a, b in m["pairs"]}
    meshes = [subdivided_ellipsoid(a, r, c, control=1, levels=2) for c, a, r in zip(centre, axes, rot)]
    mesh_pairs = {tuple(p) for p in find_contacts(meshes, GAP).pairs.tolist()}

    def precision_recall(found):
        return len(found & truth) / len(found), len(found & truth) / len(truth)

    p_vox, r_vox = precision_recall(voxel_pairs)
    p_mesh, r_mesh = precision_recall(mesh_pairs)
    assert r_vox >= 0.9  # the voxel contacts at gap + one voxel miss no touching pair ...
    assert p_vox < 0.9  # ... but take pairs up to about a voxel farther apart than the gap
    assert p_mesh >= 0.9 and r_mesh >= 0.9 and p_mesh > p_vox
