"""One rule for what layoutwarp keeps: bounded caches of results by value, per-object memos of
keys that follow an object's changes and die with it; every one of them in `CACHES`."""

from __future__ import annotations

import gc

import torch

import layoutwarp as lw
from layoutwarp.caches import CACHES, LRU, ObjectMemo, clear_caches, tensor_token


def test_every_cache_is_registered_and_cleared_in_one_place():
    img = torch.rand(1, 1, 30, 40)
    lw.simulate(img, lw.CurvLayout((0.3, 0.1)), (5, 6))  # a mesh, area weights, a layout key
    lw.simulate(
        img, lw.CurvLayout((0.3, 0.1)), (5, 6), physics=lw.SensorPhysics((6.0, 8.0), photons_per_um2=9)
    )
    names = {"meshes", "resamplers", "sensors", "sensors on devices", "layout keys", "fixed centres"}
    assert names <= set(CACHES)
    assert all(len(CACHES[n]) > 0 for n in ("resamplers", "sensors", "layout keys"))
    clear_caches()
    assert all(len(cache) == 0 for cache in CACHES.values())


def test_an_lru_keeps_the_last_used_and_a_size_of_zero_keeps_none():
    cache, built = LRU("test lru", 2), []
    for key in ("a", "b", "a", "c"):
        cache.get(key, lambda key=key: built.append(key) or key.upper())
    assert cache.keys() == ["a", "c"] and built == ["a", "b", "c"]  # b least recently used: out
    with cache.kept():
        cache.get("d", lambda: "D")
    assert cache.keys() == ["a", "c"]
    cache.get("e", lambda: "E", keep=False)
    assert "e" not in cache.keys()
    cache.maxsize = 0
    cache.clear()
    assert cache.get("f", lambda: "F") == "F" and len(cache) == 0
    del CACHES["test lru"]


def test_an_object_memo_follows_changes_and_dies_with_its_object():
    memo, calls = ObjectMemo("test memo"), []
    t = torch.zeros(3)

    def value(x):
        return lambda: calls.append(1) or float(x.sum())

    assert memo.get(t, (t._version,), value(t)) == 0.0 and memo.get(t, (t._version,), value(t)) == 0.0
    assert len(calls) == 1
    t += 1  # in place: a new version
    assert memo.get(t, (t._version,), value(t)) == 3.0 and len(calls) == 2
    del t
    gc.collect()
    assert len(memo) == 0
    del CACHES["test memo"]


def test_a_tensor_token_is_its_identity_and_version():
    a, b = torch.zeros(2), torch.zeros(2)
    first = tensor_token(a)
    assert tensor_token(a) is first and tensor_token(b) is not first
    a.add_(1)
    assert tensor_token(a) is not first
