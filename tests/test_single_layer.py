"""The single layer with a stack's total reflectance (optics/single_layer.py): a single layer
is its own equivalent, the fit reproduces the stack's Rd, targets one layer cannot reflect are
refused, and the bssrdf_single model reads the fitted layer's profiles."""
from __future__ import annotations

import numpy as np
import pytest

from dermis.optics.layer_profiles import build_profiles
from dermis.optics.layers import PRESETS
from dermis.optics.single_layer import RD_TOLERANCE, single_layer_equivalent


def test01_a_single_layer_is_its_own_equivalent():
    skin1 = PRESETS["skin1"]
    rd = build_profiles(skin1).Rd
    single, info = single_layer_equivalent(skin1, rd)
    # Rd is met to RD_TOLERANCE; |d ln Rd / d ln sigma_a| > 0.1 for skin (Rd falls by more
    # than 10 % per e-fold of absorption here), so sigma_a is met to 10 x RD_TOLERANCE
    got, want = np.asarray(single.layers[0].sigma_a), np.asarray(skin1.layers[0].sigma_a)
    assert np.all(np.abs(got / want - 1.0) < 10 * RD_TOLERANCE), (got, want)
    assert single.layers[0].eta == skin1.layers[0].eta


def test02_the_two_layer_skin_gets_a_layer_with_its_rd_and_another_shape():
    stack = PRESETS["two_layer"]
    target = build_profiles(stack).Rd
    single, info = single_layer_equivalent(stack, target)
    prof = build_profiles(single)
    assert np.all(np.abs(prof.Rd / target - 1.0) < RD_TOLERANCE)
    assert len(single.layers) == 1 and np.isinf(single.layers[0].thickness_mm)


def test03_a_target_one_layer_cannot_reflect_is_refused():
    with pytest.raises(ValueError, match="outside what one layer"):
        single_layer_equivalent(PRESETS["skin1"], [0.999, 0.2, 0.1])


def test04_the_single_layer_model_reads_the_fitted_profiles():
    import tomllib
    from dermis.pipeline.config import scene_from_dict
    from dermis.pipeline.plan import build_graph
    from scene_toml import QUICK, TINY, merge
    table = merge(tomllib.loads(QUICK.read_text()), TINY)
    table["render"]["models"] = ["bssrdf", "bssrdf_single"]
    nodes, _ = build_graph(scene_from_dict(table, where="s.toml"))
    img = nodes["render-bssrdf_single-point-high"]
    prof = nodes[img.deps["profile"]]
    assert prof.params["model"] == "single_layer" and prof.deps == {"stack": "profiles"}
    assert nodes["render-bssrdf-point-high"].deps["profile"] == "profiles"
