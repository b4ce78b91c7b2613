"""Sharded candidate mode: identical to one machine (in-process and on a local Ray cluster),
exact across shard edges, a killed actor restarted without a lost query, load failures named."""

import json
import re

import numpy as np
import pytest
import torch
from routes import route

from torchseq.maps import MapError, build_map
from torchseq.seqslam import SeqSLAM, SeqSLAMConfig

faiss = pytest.importorskip(
    "faiss", reason="candidate mode needs FAISS (pip install 'torchseq[faiss]'); not installed")

from torchseq.seqslam import sharded as sm  # noqa: E402
from torchseq.seqslam.candidates import CandidateSeqSLAM  # noqa: E402

CONFIGS = [{}, dict(match_at="start"), dict(metric="l2"), dict(enhance_window=0),
           dict(ds=5, vmin=0.5, vmax=1.5, rwindow=3), dict(speed_ratio=0.9, enhance_window=5)]


def assert_same(got, want):
    """Value for value: matches, ranking, uniqueness and best scores."""
    np.testing.assert_array_equal(got.matches.reference, want.matches.reference)
    np.testing.assert_array_equal(got.ranked, want.ranked)
    np.testing.assert_array_equal(got.matches.score, want.matches.score)
    np.testing.assert_array_equal(got.best_score, want.best_score)


def make_map(tmp_path, over, n_ref=200, n_query=40, shard_size=23, seed=5, index="flat",
             **options):
    rng = np.random.default_rng(seed)
    ref, query = route(rng, n_ref, n_query, 1.0)
    ref, query = (torch.tensor(x, dtype=torch.float32) for x in (ref, query))
    m = build_map(ref, tmp_path / "map", SeqSLAMConfig(**over), shard_size=shard_size,
                  index=index, index_options=options or None)
    return ref, query, m


# every configuration at k = 2 in the quick run; k = 8 there on the default configuration
# (the same sharding code, more centres per query), on the others in CI's slow pass
@pytest.mark.parametrize("over, k", [
    pytest.param(over, k, marks=pytest.mark.slow if k == 8 and over else (),
                 id=f"over{i}-{k}")
    for k in (2, 8) for i, over in enumerate(CONFIGS)])
def test_shards_equal_one_machine(tmp_path, over, k):
    """Shards of 23 places (trajectories span 13 rows, the enhancement 10: many cross an edge),
    spread over 1, 3 and 9 workers, batches of 7 centres: the one-machine candidate mode."""
    ref, query, m = make_map(tmp_path, over)
    config = SeqSLAMConfig(candidates=k, **over)
    want = CandidateSeqSLAM(ref, config).match_descriptors(query)
    assert (want.matches.reference >= 0).sum() > 20
    for shards in (1, 3, 9):
        got = sm.ShardedSeqSLAM(m, config, shards, use_ray=False, batch=7).match_descriptors(
            query)
        assert got.kernels["shards"] == shards
        assert_same(got, want)


@pytest.mark.parametrize("over", [{}, dict(ds=5, vmin=0.5, vmax=1.5, rwindow=3)])
def test_all_candidates_equal_exact_mode(tmp_path, over):
    ref, query, m = make_map(tmp_path, over, n_ref=120)
    got = sm.ShardedSeqSLAM(m, SeqSLAMConfig(candidates=120, **over), 4,
                            use_ray=False).match_descriptors(query)
    exact = SeqSLAM(SeqSLAMConfig(candidates=0, **over)).match_descriptors(ref, query)
    np.testing.assert_array_equal(got.matches.reference, exact.matches.reference)
    np.testing.assert_array_equal(got.ranked, exact.ranked)
    np.testing.assert_allclose(got.matches.score, exact.matches.score, rtol=1e-5, atol=1e-6)


def test_approximate_index_refined_on_the_shards(tmp_path):
    ref, query, m = make_map(tmp_path, {}, n_ref=300, index="ivf", pca_dim=16, nlist=8,
                             nprobe=2)
    config = SeqSLAMConfig(candidates=3)
    one = CandidateSeqSLAM(ref, config, index=m.index())
    sharded = sm.ShardedSeqSLAM(m, config, 5, use_ray=False)
    assert sharded.index.kind == "ivf"
    np.testing.assert_array_equal(sharded.search(query), one.search(query))
    assert_same(sharded.match_descriptors(query), one.match_descriptors(query))


def test_restarted_names_the_shards_with_a_new_process(tmp_path):
    ref, query, m = make_map(tmp_path, {}, n_ref=100)
    sharded = sm.ShardedSeqSLAM(m, SeqSLAMConfig(candidates=3), 2, use_ray=False)
    assert sharded.restarted() == []  # one process throughout
    sharded.status[1] = {**sharded.status[1], "pid": -1}  # as a Ray actor restarted elsewhere
    assert sharded.restarted() == [1]


def robots(sharded, queries, steps=None):
    """Step every query traverse as one robot of a batch; per step the (B,) decisions."""
    state, out = None, []
    for t in range(steps or len(queries[0])):
        match, state = sharded.step(torch.stack([q[t] for q in queries]), state)
        out.append(match)
    return [torch.stack([getattr(x, f) for x in out]) for f in out[0]._fields]


@pytest.mark.parametrize("over", [{}, dict(ds=5, vmin=0.5, vmax=1.5, rwindow=3)])
def test_streams_equal_streaming_candidate_mode(tmp_path, over):
    """Several robots, one state each: StreamingSeqSLAM's candidate-mode decisions."""
    from torchseq.seqslam import StreamingSeqSLAM

    ref, query, m = make_map(tmp_path, over, n_query=30)
    other = torch.tensor(route(np.random.default_rng(13), 200, 30, 1.1)[1], dtype=torch.float32)
    config = SeqSLAMConfig(candidates=3, **over)
    sharded = sm.ShardedSeqSLAM(m, config, 4, use_ray=False)
    got = robots(sharded, [query, other])
    one = StreamingSeqSLAM(ref, config, descriptors=True)
    for b, q in enumerate((query, other)):
        state, want = None, []
        for t in range(len(q)):
            match, state = one.step(q[t][None], state)
            want.append(match)
        for f, g in zip(want[0]._fields, got):
            np.testing.assert_array_equal(g[:, b], torch.cat([getattr(w, f) for w in want]),
                                          err_msg=f)
    assert (got[0] >= 0).sum() > 30
    with pytest.raises(ValueError, match="state must come from"):
        sharded.step(query[:3], sharded.initial_state(2))


def test_edge_rows_are_needed(tmp_path, monkeypatch):
    """Without its edge rows a shard cannot score trajectories that leave it: refused."""
    ref, query, m = make_map(tmp_path, {})
    monkeypatch.setattr(sm, "edge_rows", lambda start, stop, n_ref, span, window: (start, stop))
    with pytest.raises(RuntimeError, match="do not hold rows"):
        sm.ShardedSeqSLAM(m, SeqSLAMConfig(candidates=4), 3, use_ray=False).match_descriptors(
            query)


def test_shard_ranges_and_errors(tmp_path):
    ref, query, m = make_map(tmp_path, {})
    assert sm.shard_ranges(m, 3) == [(0, 69), (69, 138), (138, 200)]
    assert sm.shard_ranges(m, 9)[-1] == (184, 200)
    with pytest.raises(ValueError, match="the map has 9 shard file"):
        sm.shard_ranges(m, 10)
    with pytest.raises(ValueError, match="candidates K >= 1"):
        sm.ShardedSeqSLAM(m, SeqSLAMConfig(), 2, use_ray=False)
    sharded = sm.ShardedSeqSLAM(m, SeqSLAMConfig(candidates=2), 2, use_ray=False)
    with pytest.raises(ValueError, match="query descriptors"):
        sharded.match_descriptors(query[:, :5])
    with pytest.raises(ValueError, match="ds \\+ 1"):
        sharded.match_descriptors(query[:5])


# ------------------------------------------------------------------ on a local Ray cluster

@pytest.fixture(scope="module")
def ray_cluster():
    ray = pytest.importorskip("ray", reason="sharded matching runs on Ray (pip install "
                              "'torchseq[ray]'); not installed")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    ray.shutdown()


@pytest.mark.slow
def test_ray_actors_equal_one_machine_and_survive_killed_actors(tmp_path, ray_cluster):
    """Actor 1 is killed while its round-1 tasks are out, actor 0 during round 2: both are
    restarted, reload their shards from the map, and every query comes back the same.
    (Two actors: each restart starts a process that imports torch, slow on a loaded CI.)"""
    ref, query, m = make_map(tmp_path, {}, n_query=60)
    config = SeqSLAMConfig(candidates=4)
    want = CandidateSeqSLAM(ref, config).match_descriptors(query)
    with sm.ShardedSeqSLAM(m, config, 2, batch=16) as sharded:
        pids = [s["pid"] for s in sharded.status]
        assert_same(sharded.match_descriptors(query), want)
        memory = sharded.memory()
        assert [x["rows_bytes"] for x in memory] == [
            (b - a) * 64 * 4 for a, b in (sm.edge_rows(a, b, 200, sharded.span, 10)
                                          for a, b in sharded.ranges)]
        assert all(x["rss_bytes"] > 0 for x in memory)
        killed = []

        def kill(round_name):
            victim = 1 if round_name == "floor" else 0
            ray_cluster.kill(sharded.workers[victim], no_restart=False)
            killed.append(victim)

        sharded._on_round = kill
        got = sharded.match_descriptors(query)
        assert killed == [1, 0]
        assert_same(got, want)
        local = sm.ShardedSeqSLAM(m, config, 2, use_ray=False)  # robots: streams on Ray
        for g, w in zip(robots(sharded, [query, query.flip(0)], 20),
                        robots(local, [query, query.flip(0)], 20)):
            np.testing.assert_array_equal(g, w)
        after = ray_cluster.get([w.ready.remote() for w in sharded.workers])
        assert after[0]["pid"] != pids[0] and after[1]["pid"] != pids[1]  # restarted
        assert sharded.restarted() == [0, 1]  # what eval --shards records in metrics.json
        assert after[0]["error"] is None and after[0]["rows"] > 0  # reloaded from the map


@pytest.mark.slow
def test_ray_shard_that_cannot_load_is_named(tmp_path, ray_cluster):
    ref, query, m = make_map(tmp_path, {})
    shard = m.path / "shard-00008.npy"  # places 184..199: only the second actor reads it
    data = bytearray(shard.read_bytes())
    data[-3] ^= 0x10
    shard.write_bytes(bytes(data))
    message = (r"shard 1 \(places 92\.\.199\) could not load: .*shard-00008\.npy: checksum "
               r"mismatch")
    with pytest.raises(MapError, match=message):
        sm.ShardedSeqSLAM(m, SeqSLAMConfig(candidates=4), 2)


@pytest.mark.slow
def test_ray_eval_cli_with_shards(tmp_path, ray_cluster, capsys):
    """``eval --map MAP --shards 2`` writes the same matches as ``eval --map MAP``."""
    from torchseq.cli import main
    from torchseq.demo import make_demo

    demo = make_demo(n_reference=80, speed=0.9, seed=4)
    np.save(tmp_path / "ref.npy", demo.reference.numpy())
    np.save(tmp_path / "query.npy", demo.query.numpy())
    assert main(["map", "build", "--reference", str(tmp_path / "ref.npy"), "--out",
                 str(tmp_path / "m"), "--shard-size", "20", "--no-progress"]) == 0
    common = ["--map", str(tmp_path / "m"), "--query", str(tmp_path / "query.npy"),
              "--tolerance", "2", "--candidates", "5", "--no-progress", "--no-tensorboard"]
    assert main(["eval", *common, "--out", str(tmp_path / "one")]) == 0
    assert main(["eval", *common, "--shards", "2", "--out", str(tmp_path / "two")]) == 0
    one = (tmp_path / "one" / "matches.csv").read_text()
    assert one == (tmp_path / "two" / "matches.csv").read_text()
    assert json.loads((tmp_path / "two" / "metrics.json").read_text())["seqslam"][
        "recall_at_1"] > 0.5
    assert ray_cluster.is_initialized()  # a cluster it did not start is left running
    no_k = [a for a in common if a not in ("--candidates", "5")]
    assert main(["eval", *no_k, "--shards", "3", "--out", str(tmp_path / "x")]) == 2
    assert re.search("--shards runs candidate mode", capsys.readouterr().err)


def test_unreachable_cluster_is_one_clear_error(tmp_path, monkeypatch):
    """A Ray start that fails (here: an address nobody listens on) is one RuntimeError line."""
    ray = pytest.importorskip("ray", reason="sharded matching runs on Ray; not installed")
    ref, query, m = make_map(tmp_path, {})

    def refuse(**kwargs):
        raise Exception("The current node timed out during startup.\nmore lines")

    monkeypatch.setattr(ray, "is_initialized", lambda: False)
    monkeypatch.setattr(ray, "init", refuse)
    with pytest.raises(RuntimeError, match=r"could not start or reach the Ray cluster at "
                       r"10\.0\.0\.1:1: The current node timed out during startup\. \(start"):
        sm.ShardedSeqSLAM(m, SeqSLAMConfig(candidates=4), 2, address="10.0.0.1:1")
