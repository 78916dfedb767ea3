"""A create whose first save fails is refused — 507 naming ``store`` when the
store is full, 503 with ``Retry-After`` when it cannot be written for another
reason — and creates nothing: no session, no record, the memory budget as it
was; the sessions already saved keep their records. A 201 means the session
is in the store."""

from __future__ import annotations

import errno

import pytest

pytest.importorskip("fastapi")

from fastapi.testclient import TestClient  # noqa: E402

from hybridmpm.service import ServiceConfig, create_app  # noqa: E402
from hybridmpm.service.store import SessionStore, session_key  # noqa: E402
from hybridmpm.service.testing import step_binary  # noqa: E402


def test_a_create_whose_first_save_fails_is_refused_and_loses_nothing(tmp_path, monkeypatch):
    store = tmp_path / "store"
    app = create_app(ServiceConfig(store=str(store), max_sessions=8, max_sessions_per_client=8, save_every_s=600.0))
    real_write = SessionStore.write
    with TestClient(app) as c:
        r = c.post("/v1/sessions", json={"scene": "water2d", "solver": "mpm", "seed": 3})
        assert r.status_code == 201 and r.json()["saved_frame"] == 0
        kept = r.json()["id"]
        step_binary(c, kept, 4)
        record = (store / f"{session_key(kept)}.npz").read_bytes()
        used = c.get("/healthz").json()["memory_used"]
        for err, status in ((errno.ENOSPC, 507), (errno.EDQUOT, 507), (errno.EACCES, 503)):

            def failing(self, key, data, err=err):
                raise OSError(err, errno.errorcode[err])

            monkeypatch.setattr(SessionStore, "write", failing)
            r = c.post("/v1/sessions", json={"scene": "water2d", "solver": "mpm", "seed": 4})
            assert r.status_code == status, r.text[:300]
            detail = r.json()["detail"]
            assert isinstance(detail, str) and detail.startswith("store:") and "nothing was created" in detail, detail
            assert (status == 503) == ("retry-after" in r.headers)
            health = c.get("/healthz").json()
            assert health["sessions"] == 1 and health["memory_used"] == used
            assert sorted(p.name for p in store.iterdir() if p.suffix == ".npz") == [f"{session_key(kept)}.npz"]
            assert (store / f"{session_key(kept)}.npz").read_bytes() == record
        monkeypatch.setattr(SessionStore, "write", real_write)
        r = c.post("/v1/sessions", json={"scene": "water2d", "solver": "mpm", "seed": 4})
        assert r.status_code == 201 and r.json()["saved_frame"] == 0
        assert (store / f"{session_key(r.json()['id'])}.npz").is_file()
        assert c.get(f"/v1/sessions/{kept}").json()["frame"] == 4


def test_a_ray_actor_whose_first_save_fails_answers_the_error_and_is_not_created(tmp_path, monkeypatch):
    """The Ray backend's create waits for the actor's ``ready``: an actor whose
    first save failed answers ``StoreSaveError`` with the save's errno (the
    route's 507 naming ``store`` when full, 503 otherwise), not its facts (a 201
    of a session that is not in the store). The actor is built in this process
    (Ray's runtime context stubbed), so the store's write can be made to fail."""
    pytest.importorskip("ray")
    import types

    import ray

    from hybridmpm.service.ray_backend import actor as actor_mod
    from hybridmpm.service.ray_backend.manager import error_from
    from hybridmpm.service.sessions import StoreSaveError

    monkeypatch.setattr(ray, "get_runtime_context", lambda: types.SimpleNamespace(was_current_actor_reconstructed=False))
    store = tmp_path / "store"
    SessionStore(str(store)).open()
    settings = {"store": str(store), "save_every_s": 600.0, "idle_ttl_s": 600.0, "max_checkpoint_bytes": 1 << 28, "memory_budget": 1 << 30, "namespace": "t"}
    for err, full in ((errno.ENOSPC, True), (errno.EACCES, False)):

        def failing(self, key, data, err=err):
            raise OSError(err, errno.errorcode[err])

        monkeypatch.setattr(SessionStore, "write", failing)
        a = actor_mod.SessionActor(session_key(f"s{err}"), "water2d", 3, "mpm", 0.8, "client", settings)
        out = a.ready()
        assert out[0] == "err" and out[1] == "StoreSaveError", out
        e = error_from(*out[1:])
        assert isinstance(e, StoreSaveError) and e.full is full and errno.errorcode[err] in e.why
        assert not any(p.suffix == ".npz" for p in store.iterdir())
    monkeypatch.setattr(SessionStore, "write", lambda self, key, data: None)
    ok = actor_mod.SessionActor(session_key("sok"), "water2d", 3, "mpm", 0.8, "client", settings)
    assert ok.ready()[0] == "ok"
    ok.closing = (1000, "test over")
