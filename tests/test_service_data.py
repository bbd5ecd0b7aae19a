"""/v1/jobs/{id}/data and /background: uploads, background subtraction, scan-directory files."""

import io

import httpx
import numpy as np
import pytest

from service_support import ServerThread, client, p2d, server  # noqa: F401 - fixtures


def npy(a, **kw):
    buf = io.BytesIO()
    np.save(buf, a, **kw)
    return buf.getvalue()


NPY = {"content-type": "application/x-npy"}


def test_upload_replace_and_remove_data(client, p2d):  # noqa: F811
    job = client.create_job(p2d.geometry, surfaces=p2d.init)
    with pytest.raises(ValueError, match="no data"):  # RemoteValueError (409) is a ValueError
        job.objective(p2d.init)
    job.set_data(p2d.data)
    f, grads = job.objective(p2d.init)
    fl, gl = p2d.projector.objective(p2d.init, p2d.data)
    assert f == fl
    job.set_data(None)
    assert not job.info()["has_data"]
    job.delete()


def test_background_is_subtracted_from_the_data(client, p2d):  # noqa: F811
    background = np.random.default_rng(1).uniform(0, 2, p2d.geometry.shape).astype(np.float32)
    raw = p2d.data + background
    job = client.create_job(p2d.geometry, data=raw, background=background, surfaces=p2d.init)
    f, grads = job.objective(p2d.init)
    fl, gl = p2d.projector.objective(p2d.init, np.subtract(raw, background, dtype=np.float32))
    assert f == pytest.approx(fl, rel=1e-12)
    for a, b in zip(grads, gl):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-12)
    job.set_background(None)  # now the raw data is the target
    assert job.objective(p2d.init)[0] == pytest.approx(p2d.projector.objective(p2d.init, raw)[0], rel=1e-12)
    job.delete()


def test_bad_uploads(server, client, p2d):  # noqa: F811
    job = client.create_job(p2d.geometry, surfaces=p2d.init)
    url = f"{server.url}/v1/jobs/{job.id}/data"
    cases = [
        (npy(p2d.data[:, :10]), NPY, 422, "shape"),
        (npy(p2d.data.astype(np.complex64)), NPY, 422, "dtype"),
        (npy(np.full(p2d.geometry.shape, np.nan, np.float32)), NPY, 422, "nan"),
        (npy(np.array([object()] * 3), allow_pickle=True), NPY, 422, "dtype"),
        (npy(p2d.data)[:-7], NPY, 400, "truncated"),
        (b"not an array", NPY, 400, ".npy"),
        (npy(p2d.data), {"content-type": "text/csv"}, 415, "content-type"),
        (npy(p2d.data), {}, 415, "content-type"),
        (b'{"file": "x.npy"}', {"content-type": "application/json"}, 422, "scan directory"),
    ]
    for body, headers, status, words in cases:
        r = httpx.put(url, content=body, headers=headers)
        assert r.status_code == status, (words, r.text)
        assert words in r.json()["detail"].lower(), r.json()
    assert not job.info()["has_data"]
    job.delete()


def test_load_data_from_the_scan_directory(tmp_path, p2d):  # noqa: F811
    np.save(tmp_path / "scan.npy", p2d.data)
    np.savez(tmp_path / "scans.npz", sino=p2d.data, other=p2d.data[:2])
    (tmp_path / "sub").mkdir()
    with ServerThread(scan_dir=tmp_path) as s:
        from bubsub.clients.remote.client import ProjectorClient

        with ProjectorClient(s.url) as c:
            job = c.create_job(p2d.geometry, surfaces=p2d.init)
            url = f"{s.url}/v1/jobs/{job.id}/data"
            assert httpx.put(url, json={"file": "scan.npy"}).status_code == 200
            assert job.objective(p2d.init)[0] == p2d.projector.objective(p2d.init, p2d.data)[0]
            assert httpx.put(url, json={"file": "scans.npz", "key": "sino"}).status_code == 200
            for body, words in [({"file": "scans.npz"}, "key"), ({"file": "../secret.npy"}, "outside"),
                                ({"file": "sub"}, "not found"), ({"file": "nope.npy"}, "not found")]:
                r = httpx.put(url, json=body)
                assert r.status_code == 422 and words in r.json()["detail"], r.text
