"""/v1/jobs/{id}/forward, /vjp, /objective: remote equals local; bad inputs give 4xx."""

import io
import json
import zipfile

import httpx
import numpy as np
import pytest

from service_support import client, p2d, p3d, server  # noqa: F401 - fixtures


def npy(a, **kw):
    buf = io.BytesIO()
    np.save(buf, a, **kw)
    return buf.getvalue()


def npz(**arrays):
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


@pytest.mark.parametrize("which, supersampling", [("2d", 1), ("3d", 1), ("3d", 2)])
def test_remote_equals_local(client, p2d, p3d, which, supersampling):  # noqa: F811
    from bubsub.core import MeshProjector

    p = p2d if which == "2d" else p3d
    local = MeshProjector(p.geometry, supersampling=supersampling)
    data = local.forward(p.truth)
    job = client.create_job(p.geometry, data=data, surfaces=p.init, supersampling=supersampling)
    items = [s.with_vertices(s.vertices * 1.01) for s in p.init]  # an iterate other than the first

    fwd = job.forward(items)
    assert fwd.dtype == np.float32 and fwd.shape == p.geometry.shape
    np.testing.assert_array_equal(fwd, local.forward(items))

    residual = np.random.default_rng(0).normal(size=p.geometry.shape).astype(np.float32)
    for a, b in zip(job.vjp(items, residual), local.vjp(items, residual)):
        assert a.dtype == np.float64 and a.shape == b.shape
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)

    f, grads = job.objective(items)
    fl, gl = local.objective(items, data)
    assert f == pytest.approx(fl, rel=1e-12)
    for a, b in zip(grads, gl):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)

    other = data * np.float32(0.5)  # explicit data overrides the job's
    f2, g2 = job.objective(items, other)
    fl2, gl2 = local.objective(items, other)
    assert f2 == pytest.approx(fl2, rel=1e-12)
    np.testing.assert_allclose(np.concatenate(g2), np.concatenate(gl2), rtol=1e-12, atol=1e-12)
    job.delete()


def test_objective_header_and_multipart(server, client, p2d):  # noqa: F811
    job = client.create_job(p2d.geometry, data=p2d.data, surfaces=p2d.init)
    x = np.concatenate([s.vertices for s in p2d.init])
    r = httpx.post(f"{server.url}/v1/jobs/{job.id}/objective",
                   files={"vertices": ("v.npy", npy(x), "application/x-npy")})
    assert r.status_code == 200 and r.headers["content-type"] == "application/x-npz"
    z = np.load(io.BytesIO(r.content))
    assert float(r.headers["x-objective"]) == float(z["value"])
    assert z["gradient"].shape == x.shape
    job.delete()


def test_bad_compute_inputs_are_4xx_with_a_message(server, client, p2d):  # noqa: F811
    job = client.create_job(p2d.geometry, surfaces=p2d.init)
    base = f"{server.url}/v1/jobs/{job.id}"
    x = np.concatenate([s.vertices for s in p2d.init])
    nan = x.copy()
    nan[3, 1] = np.nan
    bomb = io.BytesIO()
    with zipfile.ZipFile(bomb, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("vertices.npy", npy(np.zeros((5 << 20,), np.float64)))
    N, Z = "application/x-npy", "application/x-npz"
    cases = [
        ("forward", npy(x.astype(np.int64)), N, 422, "dtype"),
        ("forward", npy(x[:5]), N, 422, "shape"),
        ("forward", npy(x[:, :1]), N, 422, "shape"),
        ("forward", npy(nan), N, 422, "nan"),
        ("forward", npy(x)[:-3], N, 400, "truncated"),
        ("forward", npy(x) + b"xx", N, 400, "trailing"),
        ("forward", npy(np.array([{"a": 1}]), allow_pickle=True), N, 422, "dtype"),
        ("forward", b"\x93NUMPY\x01\x00\xff\xffgarbage", N, 400, "header"),
        ("forward", npy(x), "text/plain", 415, "content-type"),
        ("forward", json.dumps(x.tolist()).encode(), "application/json", 415, "content-type"),
        ("forward", b"PK\x03\x04broken", Z, 400, "zip"),
        ("forward", bomb.getvalue(), Z, 413, "inflates"),
        ("forward", npz(vertices=x, extra=x), Z, 422, "unexpected"),
        ("vjp", npy(x), N, 422, "missing"),
        ("vjp", npz(vertices=x, residual=np.zeros((3, 3), np.float32)), Z, 422, "shape"),
        ("vjp", npz(vertices=x, residual=np.full(p2d.geometry.shape, np.inf)), Z, 422, "nan"),
        ("objective", npy(x), N, 409, "no data"),
        ("objective", npz(vertices=x, data=np.zeros(7)), Z, 422, "shape"),
        ("objective", npz(data=p2d.data), Z, 422, "missing"),
        ("objective", b"--zz\r\nContent-Disposition: form-data; name=\"vertices\"\r\n\r\n" + npy(x),
         "multipart/form-data; boundary=zz", 400, "truncated"),
        ("objective", b"--zz\r\n\r\nabc\r\n--zz--\r\n", "multipart/form-data; boundary=zz", 400, "name"),
    ]
    for op, body, ctype, status, words in cases:
        r = httpx.post(f"{base}/{op}", content=body, headers={"content-type": ctype})
        assert r.status_code == status, (op, words, r.status_code, r.text)
        err = r.json()
        assert words in err["detail"].lower(), (words, err)
    # unknown job, also with a body that would be invalid
    r = httpx.post(f"{server.url}/v1/jobs/not-a-job/forward", content=b"x", headers={"content-type": N})
    assert r.status_code == 404 and r.json()["code"] == "unknown_job"
    # the job still works after all that
    assert job.forward(p2d.init).shape == p2d.geometry.shape
    job.delete()


def test_client_checks_items_against_the_topology(client, p2d):  # noqa: F811
    job = client.create_job(p2d.geometry, data=p2d.data, surfaces=p2d.init)
    with pytest.raises(ValueError, match="3 surfaces"):
        job.objective(p2d.init[:2])
    with pytest.raises(ValueError, match="attenuation"):
        job.objective([s.with_attenuation(2.0) for s in p2d.init])
    with pytest.raises(ValueError, match="residual"):
        job.vjp(p2d.init, np.zeros(4))
    with pytest.raises(TypeError, match="SubdivisionSurface"):
        job.forward([s.fine() for s in p2d.init])  # polygons, not subdivision surfaces
    job.delete()
