"""remote_projectors: the jobs it makes are deleted and its connection closed however the block ends."""

import pytest

from bubsub.clients.remote import client as remote_client
from bubsub.clients.remote.jobs import remote_projectors


class FakeServer:
    """Stands in for a projector server: records the jobs made, deleted, and the connection's state."""

    def __init__(self, failing_delete=()):
        self.made, self.deleted, self.closed, self.failing_delete = [], [], False, set(failing_delete)
        self.options = []

    def connect(self, url, token=None):
        self.url, self.token = url, token
        return self

    # the ProjectorClient part
    def create_job(self, geometry, data=None, surfaces=(), supersampling=1):
        job = FakeJob(self, len(self.made))
        self.made.append(job)
        self.options.append((geometry, data, tuple(surfaces), supersampling))
        return job

    def close(self):
        self.closed = True


class FakeJob:
    def __init__(self, server, number):
        self.server, self.number = server, number

    def delete(self):
        if self.number in self.server.failing_delete:
            raise RuntimeError(f"job {self.number} is gone")
        self.server.deleted.append(self.number)


@pytest.fixture
def server(monkeypatch):
    fake = FakeServer()
    monkeypatch.setattr(remote_client, "connect", fake.connect)
    return fake


def test_no_server_yields_no_factory(server):
    with remote_projectors(None) as factory:
        assert factory is None
    assert server.made == [] and not server.closed and not hasattr(server, "url")


def test_the_jobs_are_made_as_asked_and_deleted_on_exit(server):
    with remote_projectors("http://fit.example:8000", "secret", supersampling=2) as factory:
        a = factory("g1", "d1", ["s1"])
        b = factory("g2", "d2", ["s2", "s3"])
        assert (a.number, b.number) == (0, 1) and not server.closed
    assert (server.url, server.token) == ("http://fit.example:8000", "secret")
    assert server.options == [("g1", "d1", ("s1",), 2), ("g2", "d2", ("s2", "s3"), 2)]
    assert server.deleted == [0, 1] and server.closed


@pytest.mark.parametrize("stop", [ValueError("the fit failed"), KeyboardInterrupt()])
def test_an_error_or_ctrl_c_still_cleans_up_and_is_raised(server, stop):
    with pytest.raises(type(stop)):
        with remote_projectors("http://fit.example:8000") as factory:
            factory("g", "d", [])
            raise stop
    assert server.deleted == [0] and server.closed


def test_a_job_that_cannot_be_deleted_is_reported_not_raised(monkeypatch):
    fake = FakeServer(failing_delete={0})
    monkeypatch.setattr(remote_client, "connect", fake.connect)
    told = []
    with remote_projectors("http://fit.example:8000", on_cleanup_error=told.append) as factory:
        factory("g", "d", [])
        factory("g", "d", [])
    assert [str(e) for e in told] == ["job 0 is gone"]
    assert fake.deleted == [1] and fake.closed
