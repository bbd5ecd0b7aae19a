"""/v1/jobs: create, inspect, list, delete; invalid job definitions."""

import io
import json

import httpx
import numpy as np
import pytest

from service_support import client, p2d, p3d, server  # noqa: F401 - fixtures


def npy(a):
    buf = io.BytesIO()
    np.save(buf, a, allow_pickle=False)
    return buf.getvalue()


def geometry_json(g):
    return {"kind": g.kind, "vectors": g.vectors.tolist(), "det_rows": g.det_rows, "det_cols": g.det_cols}


def spec_2d(p, **extra):
    return {"geometry": geometry_json(p.geometry),
            "surfaces": [{"n_control": 9, "levels": 2, "attenuation": 1.0, "count": len(p.init)}], **extra}


def test_create_json_inspect_list_delete(server, p2d):  # noqa: F811
    r = httpx.post(f"{server.url}/v1/jobs", json=spec_2d(p2d))
    assert r.status_code == 201, r.text
    info = r.json()
    assert r.headers["location"] == f"/v1/jobs/{info['id']}"
    assert len(info["id"]) >= 22  # secrets.token_urlsafe(18): 144 random bits
    assert info["projection_shape"] == list(p2d.geometry.shape)
    assert info["vertices_shape"] == [27, 2] and info["n_surfaces"] == 3
    assert info["surfaces"][0]["n_fine"] == 36 and not info["has_data"]
    got = httpx.get(f"{server.url}/v1/jobs/{info['id']}").json()
    assert got["id"] == info["id"] and got["memory_bytes"] > 0
    ids = [j["id"] for j in httpx.get(f"{server.url}/v1/jobs").json()["jobs"]]
    assert info["id"] in ids
    assert httpx.delete(f"{server.url}/v1/jobs/{info['id']}").status_code == 204
    r = httpx.get(f"{server.url}/v1/jobs/{info['id']}")
    assert r.status_code == 404 and r.json()["code"] == "unknown_job"
    assert httpx.delete(f"{server.url}/v1/jobs/{info['id']}").status_code == 404


def test_create_multipart_with_arrays(server, p3d):  # noqa: F811
    faces = np.asarray(p3d.init[0].control_faces).tolist()
    meta = {"geometry": geometry_json(p3d.geometry),
            "surfaces": [{"n_control": 12, "faces": faces, "levels": 2, "attenuation": 1.0, "count": 2}]}
    x = np.concatenate([s.vertices for s in p3d.init])
    files = {"job": (None, json.dumps(meta), "application/json"),
             "vertices": ("v.npy", npy(x), "application/x-npy"),
             "data": ("d.npy", npy(p3d.data), "application/x-npy"),
             "background": ("b.npy", npy(np.zeros_like(p3d.data)), "application/x-npy")}
    r = httpx.post(f"{server.url}/v1/jobs", files=files)
    assert r.status_code == 201, r.text
    info = r.json()
    assert info["has_data"] and info["has_background"] and info["ndim"] == 3
    assert info["surfaces"][0]["n_fine"] == 162 and info["surfaces"][0]["n_faces"] == 20
    assert info["memory_bytes"] >= 3 * p3d.data.nbytes
    httpx.delete(f"{server.url}/v1/jobs/{info['id']}")


def test_create_3d_without_vertices_builds_on_first_call(server, p3d):  # noqa: F811
    faces = np.asarray(p3d.init[0].control_faces).tolist()
    meta = {"geometry": geometry_json(p3d.geometry),
            "surfaces": [{"n_control": 12, "faces": faces, "attenuation": 1.0, "count": 2}]}
    info = httpx.post(f"{server.url}/v1/jobs", json=meta).json()
    assert info["surfaces"][0]["n_fine"] is None
    x = np.concatenate([s.vertices for s in p3d.truth])
    r = httpx.post(f"{server.url}/v1/jobs/{info['id']}/forward", content=npy(x),
                   headers={"content-type": "application/x-npy"})
    assert r.status_code == 200
    np.testing.assert_array_equal(np.load(io.BytesIO(r.content)), p3d.data)
    httpx.delete(f"{server.url}/v1/jobs/{info['id']}")


def _bad(server, body=None, **kw):  # noqa: F811
    r = httpx.post(f"{server.url}/v1/jobs", **({"json": body} if body is not None else kw))
    assert 400 <= r.status_code < 500, (r.status_code, r.text)
    err = r.json()
    assert err["code"] and err["detail"]
    return r.status_code, err


@pytest.mark.parametrize("mutate, status, words", [
    (lambda s: s["geometry"].update(kind="helical"), 422, "kind"),
    (lambda s: s["geometry"].update(vectors=[[1.0, 2.0]]), 422, "vectors"),
    (lambda s: s["geometry"].update(det_rows=5), 422, "det_rows"),
    (lambda s: s["geometry"]["vectors"][0].__setitem__(0, float("nan")), 422, "nan"),
    (lambda s: s["surfaces"][0].update(n_control=2), 422, "n_control"),
    (lambda s: s["surfaces"][0].update(faces=[[0, 1, 2]]), 422, "faces"),
    (lambda s: s["surfaces"][0].update(levels=9), 422, "levels"),
    (lambda s: s.update(supersampling=0), 422, "supersampling"),
    (lambda s: s.update(surfaces=[]), 422, "surfaces"),
    (lambda s: s.update(extra=1), 422, "extra"),
])
def test_invalid_job_definitions(server, p2d, mutate, status, words):  # noqa: F811
    spec = spec_2d(p2d)
    mutate(spec)
    body = json.dumps(spec, allow_nan=True).encode()
    code, err = _bad(server, content=body, headers={"content-type": "application/json"})
    assert code == status and words in err["detail"].lower(), err


def test_invalid_3d_topologies(server, p3d):  # noqa: F811
    g = geometry_json(p3d.geometry)
    faces = np.asarray(p3d.init[0].control_faces)
    x = npy(np.concatenate([s.vertices for s in p3d.init]))

    def create(faces_, vertices=x, n=12):
        meta = {"geometry": g, "surfaces": [{"n_control": n, "faces": faces_, "attenuation": 1.0, "count": 2}]}
        files = {"job": (None, json.dumps(meta), "application/json"), "vertices": ("v.npy", vertices, "application/x-npy")}
        return _bad(server, files=files)

    assert "out of range" in create((faces + 5).tolist())[1]["detail"]
    assert "closed" in create(faces[:-1].tolist())[1]["detail"]
    assert "inward" in create(faces[:, ::-1].tolist())[1]["detail"]
    code, err = create(faces.tolist(), vertices=npy(np.zeros((5, 3))))
    assert code == 422 and "(24, 3)" in err["detail"]
    code, err = _bad(server, {"geometry": g, "surfaces": [{"n_control": 12, "attenuation": 1.0}]})
    assert "faces" in err["detail"]


def test_wrong_bodies(server, p2d):  # noqa: F811
    assert _bad(server, content=b"{", headers={"content-type": "application/json"})[0] == 400
    assert _bad(server, content=b"hello", headers={"content-type": "text/plain"})[0] == 415
    code, err = _bad(server, files={"vertices": ("v.npy", npy(np.zeros((27, 2))), "application/x-npy")})
    assert code == 422 and "job" in err["detail"]
    body = (b"--b\r\nContent-Disposition: form-data; name=\"job\"\r\n\r\n{}")
    code, err = _bad(server, content=body, headers={"content-type": "multipart/form-data; boundary=b"})
    assert code == 400 and "truncated" in err["detail"]


def test_client_create_job_groups_surfaces(client, p2d, p3d):  # noqa: F811
    job = client.create_job(p2d.geometry, data=p2d.data, surfaces=p2d.init)
    info = job.info()
    assert info["surfaces"] == [{"n_control": 9, "n_faces": None, "levels": 2, "attenuation": 1.0,
                                 "count": 3, "n_fine": 36}]
    job.delete()
    assert job.id is None
    mixed = [p3d.init[0], p3d.init[1].with_attenuation(0.5)]
    job = client.create_job(p3d.geometry, surfaces=mixed, supersampling=2)
    assert [s["count"] for s in job.info()["surfaces"]] == [1, 1]
    assert job.info()["supersampling"] == 2
    job.delete()
