import numpy as np
import pytest

from facepipe.errors import InputError
from facepipe.pipeline.cross_validation import expression_groups, holdout_folds


def test_left_and_right_halves_share_a_group():
    names = ["browDown_L", "browDown_R", "jawOpen", "mouthSmileLeft", "mouthSmileRight", "smile_l"]
    g = expression_groups(names)
    assert g[0] == g[1] and g[3] == g[4]
    assert len(set(g.tolist())) == 4


def test_folds_cover_every_example_once_and_keep_pairs_together():
    names = [f"e{i}_L" for i in range(5)] + [f"e{i}_R" for i in range(5)] + ["jawOpen", "pucker"]
    folds = holdout_folds(names, 4)
    flat = np.concatenate(folds)
    assert sorted(flat.tolist()) == list(range(len(names)))
    for f in folds:
        held = {names[i] for i in f}
        for n in held:
            if n.endswith("_L"):
                assert n[:-2] + "_R" in held
    with pytest.raises(InputError, match="--holdout"):
        holdout_folds(names, len(names))
