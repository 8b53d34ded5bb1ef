"""Stage graph and cache semantics on toy stages (the product has only real stages)."""
import json
from pathlib import Path

import numpy as np
import pytest

from dermis.pipeline.artifacts import LayerProfile
from dermis.pipeline.errors import CacheLockedError
from dermis.pipeline.graph import Node, StageResult, execute, plan_order
from dermis.pipeline.store import Store

VERSION = 1          # toy stages live in this module: its source text enters their keys
CALLS = []


class Ctx:
    out_dir = None
    progress = None
    device_description = "host"
    build_seconds = 0.0


def _profile(value):
    a = np.full(3, float(value))
    return LayerProfile(np.linspace(0, 1, 4), np.ones((4, 3)) * value, np.zeros((4, 3)), a, a, a, a)


def toy_graph(a=1.0, b=2.0, fail_in=None):
    """a -> double -> add_b ; c independent."""
    def source(inputs, ctx):
        CALLS.append("source")
        return StageResult(_profile(a))

    def double(inputs, ctx):
        CALLS.append("double")
        if fail_in == "double":
            raise KeyboardInterrupt  # a run killed mid-stage
        return StageResult(_profile(inputs["source"].Rd[0] * 2))

    def add_b(inputs, ctx):
        CALLS.append("add_b")
        (ctx.out_dir / "note.txt").write_text("x")
        return StageResult(_profile(inputs["double"].Rd[0] + b), files=["note.txt"])

    def other(inputs, ctx):
        CALLS.append("other")
        return StageResult(_profile(7))

    mod = __name__
    nodes = {
        "source": Node("source", "source", mod, {"a": a}, (), source),
        "double": Node("double", "double", mod, {}, ("source",), double),
        "add_b": Node("add_b", "add_b", mod, {"b": b}, ("double",), add_b),
        "other": Node("other", "other", mod, {"k": 1}, (), other),
    }
    return nodes


def run(store, targets=("add_b",), **kw):
    CALLS.clear()
    nodes = toy_graph(**{k: v for k, v in kw.items() if k in ("a", "b", "fail_in")})
    return execute(nodes, list(targets), store, Ctx(), force=kw.get("force", ()),
                   dry_run=kw.get("dry_run", False))


def test01_plan_order_is_topological_and_minimal():
    order = plan_order(toy_graph(), ["add_b"])
    assert order == ["source", "double", "add_b"]      # "other" is not needed: never planned


def test02_second_run_executes_nothing(tmp_path):
    store = Store(tmp_path)
    first = run(store)
    assert first.ran() == ["source", "double", "add_b"] and CALLS == first.ran()
    second = run(store)
    assert second.ran() == [] and CALLS == []
    assert second.cached() == ["source", "double", "add_b"]


def test03_changing_one_parameter_reruns_exactly_downstream(tmp_path):
    store = Store(tmp_path)
    run(store)
    s = run(store, b=3.0)
    assert s.ran() == ["add_b"]
    s = run(store, a=5.0, b=3.0)
    assert s.ran() == ["source", "double", "add_b"]
    s = run(store, a=1.0, b=2.0)                       # back to the first values: all cached
    assert s.ran() == []


def test04_results_flow_through_cache(tmp_path):
    store = Store(tmp_path)
    s = run(store, a=1.5, b=2.0)
    rep = {r.id: r for r in s.nodes}["add_b"]
    from dermis.pipeline.artifacts import load
    assert load(rep.path).Rd[0] == pytest.approx(1.5 * 2 + 2.0)


def test05_interrupted_stage_leaves_nothing_trusted(tmp_path):
    store = Store(tmp_path)
    with pytest.raises(KeyboardInterrupt):
        run(store, fail_in="double")
    assert (tmp_path / "source").is_dir()              # finished before the kill: kept
    assert not (tmp_path / "double").exists()          # unfinished: nothing under its name
    s = run(store)
    assert s.ran() == ["double", "add_b"]


def test06_status_names_the_reason(tmp_path):
    store = Store(tmp_path)
    run(store)
    s = run(store, b=4.0, dry_run=True)
    by_id = {r.id: r for r in s.nodes}
    assert by_id["add_b"].status == "stale" and "config_changed b" in by_id["add_b"].reasons
    assert by_id["source"].status == "cached" and by_id["source"].reasons == []
    assert CALLS == []                                  # status computes nothing
    s = run(store, a=9.0, dry_run=True)
    reasons = {r.id: r.reasons for r in s.nodes}
    assert reasons["source"] == ["config_changed a"]
    assert reasons["double"] == ["upstream_changed source (stale)"]


def test07_force_reruns_that_stage_only(tmp_path):
    store = Store(tmp_path)
    run(store)
    s = run(store, force=("double",))
    assert s.ran() == ["double"]


def test08_runs_share_the_cache_and_clean_waits_for_them(tmp_path):
    store = Store(tmp_path)
    with store.locked():
        with Store(tmp_path).locked():                  # a second run (or Dask worker) may share
            pass
        with pytest.raises(CacheLockedError, match="another dermis process holds it"):
            with Store(tmp_path).locked(exclusive=True):  # clean is refused while a run holds it
                pass
    with Store(tmp_path).locked(exclusive=True):        # released afterwards
        pass


def test09_metadata_records_timing_and_key(tmp_path):
    store = Store(tmp_path)
    s = run(store)
    rep = {r.id: r for r in s.nodes}["add_b"]
    meta = json.loads((tmp_path / "add_b" / rep.key / "meta.json").read_text())
    assert meta["key"] == rep.key and meta["seconds"] >= 0 and meta["files"] == ["note.txt"]
    assert meta["parts"]["params"] == {"b": 2.0}


def test10_debris_of_dead_processes_is_removed_live_work_is_kept(tmp_path):
    import os
    from dermis.pipeline.store import _host
    store = Store(tmp_path)
    dead = tmp_path / ".tmp" / "deadbeef"                              # an old run's leftovers
    live = tmp_path / ".tmp" / f"{_host()}-{os.getpid()}-cafe"         # this process: in use
    other = tmp_path / ".tmp" / "otherhost-123-beef"                   # another machine's
    for d in (dead, live, other):
        d.mkdir(parents=True)
    with store.locked():
        assert not dead.exists() and live.exists() and other.exists()


def _entry(tmp_path, nid):
    return next((tmp_path / nid).iterdir())


@pytest.mark.parametrize("damage", ["delete", "truncate", "flip"])
def test11_a_damaged_entry_is_reported_and_rebuilt_never_used(tmp_path, damage):
    store = Store(tmp_path)
    run(store)
    data = _entry(tmp_path, "double") / "data.npz"
    if damage == "delete":
        data.unlink()
    elif damage == "truncate":
        data.write_bytes(data.read_bytes()[:40])
    else:
        raw = bytearray(data.read_bytes())
        raw[len(raw) // 2] ^= 0xFF
        data.write_bytes(bytes(raw))
    status = {r.id: r for r in run(store, dry_run=True).nodes}
    assert status["double"].status == "stale" and status["double"].reasons[0].startswith("corrupted")
    assert status["source"].status == "cached"
    notices = []
    CALLS.clear()
    nodes = toy_graph()
    s = execute(nodes, ["add_b"], store, Ctx(), notice=notices.append)
    assert s.ran() == ["double"] and CALLS == ["double"]   # same key: add_b's entry stays valid
    assert len(notices) == 1 and "double" in notices[0] and "rebuilding" in notices[0]
    assert store.verify("double", s.nodes[1].key) is None


def test12_one_key_written_twice_leaves_one_valid_entry(tmp_path):
    """Two writers of the same key (e.g. two processes): the second finds a valid entry and
    drops its own copy; the entry is intact and the temporary folders are gone."""
    store = Store(tmp_path)
    for value in ("first", "second"):
        with store.writing("n", "k") as tmp:
            (tmp / "x.txt").write_text(value)
            (tmp / "meta.json").write_text("{}")
    assert store.verify("n", "k") is None
    assert (tmp_path / "n" / "k" / "x.txt").read_text() == "first"
    assert not list((tmp_path / ".tmp").iterdir())


def test13_non_finite_artifacts_are_refused(tmp_path):
    from dermis.pipeline.graph import StageFailure
    store = Store(tmp_path)

    def nan_stage(inputs, ctx):
        return StageResult(_profile(float("nan")))

    nodes = {"s": Node("s", "s", __name__, {}, (), nan_stage)}
    with pytest.raises(StageFailure, match="non-finite"):
        execute(nodes, ["s"], store, Ctx())
    assert not (tmp_path / "s").exists()


def _wide_graph(barrier, log, fail=None):
    """root -> (left, right) -> join: left and right are independent; each waits on
    ``barrier`` so that they pass only if both run at the same time."""
    import threading

    def stage(name, value):
        def fn(inputs, ctx):
            log.append((name, "start", threading.get_ident(), sorted(inputs)))
            if name in ("left", "right"):
                barrier.wait(timeout=10)           # BrokenBarrierError when run one by one
            if name == fail:
                raise RuntimeError(f"{name} failed")
            total = value + sum(float(p.Rd[0]) for p in inputs.values())
            (ctx.out_dir / "who.txt").write_text(name)   # each node its own out_dir
            log.append((name, "end", threading.get_ident(), str(ctx.out_dir)))
            return StageResult(_profile(total), files=["who.txt"])
        return fn

    return {
        "root": Node("root", "root", __name__, {"v": 1}, (), stage("root", 1.0)),
        "left": Node("left", "left", __name__, {"v": 2}, ("root",), stage("left", 2.0)),
        "right": Node("right", "right", __name__, {"v": 3}, ("root",), stage("right", 3.0)),
        "join": Node("join", "join", __name__, {"v": 4}, ("left", "right"), stage("join", 4.0)),
    }


def test14_jobs_run_independent_nodes_at_once_in_dependency_order(tmp_path):
    """jobs=2: the two independent nodes meet at a barrier (impossible one by one), every node
    starts after its inputs ended, and the results equal the serial run's."""
    import threading
    log: list = []
    s = execute(_wide_graph(threading.Barrier(2), log), ["join"], Store(tmp_path / "a"),
                Ctx(), jobs=2)
    assert sorted(s.ran()) == ["join", "left", "right", "root"]
    events = [(name, what) for name, what, *_ in log]
    for node, deps in (("left", ["root"]), ("right", ["root"]), ("join", ["left", "right"])):
        start = events.index((node, "start"))
        assert all(events.index((d, "end")) < start for d in deps)
    starts = {name: rest[1] for name, what, *rest in log if what == "start"}
    assert starts["join"] == ["left", "right"]
    out_dirs = {name: rest[1] for name, what, *rest in log if what == "end"}
    assert len(set(out_dirs.values())) == 4
    serial_log: list = []
    s1 = execute(_wide_graph(threading.Barrier(1), serial_log), ["join"], Store(tmp_path / "b"),
                 Ctx(), jobs=1)
    for a, b in zip(s.nodes, s1.nodes):
        assert a.id == b.id and a.key == b.key
        assert json.loads((Path(a.path) / "meta.json").read_text())["checksums"] == \
            json.loads((Path(b.path) / "meta.json").read_text())["checksums"]


def test15_one_failing_node_stops_new_work_and_leaves_the_rest_valid(tmp_path):
    """A node failing while its sibling runs: the failure is raised, the sibling finishes and
    is cached, nothing downstream starts, and a rerun builds only what is missing."""
    import threading
    from dermis.pipeline.graph import StageFailure
    store = Store(tmp_path)
    log: list = []
    with pytest.raises(StageFailure, match="left failed"):
        execute(_wide_graph(threading.Barrier(2), log, fail="left"), ["join"], store, Ctx(),
                jobs=2)
    assert ("join", "start") not in [(n, w) for n, w, *_ in log]
    log.clear()
    s = execute(_wide_graph(threading.Barrier(1), log), ["join"], store, Ctx(), jobs=2)
    assert sorted(s.ran()) == ["join", "left"] and sorted(s.cached()) == ["right", "root"]
    assert not list((tmp_path / ".tmp").iterdir())
