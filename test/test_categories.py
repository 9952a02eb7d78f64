"""The category file: splits as one range or a list of ranges, never overlapping."""

from __future__ import annotations

import pytest
import yaml

from w2e_ros.core.dataset.categories import UnknownCategoryError, load_categories


def _write(tmp_path, splits: dict, name: str = "cats.yaml") -> str:
    raw = {"categories": ["cabinet", "faucet", "window", "kettle"],
           "splits": splits,
           "combinations": {"cfw": ["cabinet", "faucet", "window"]},
           "default_combination": "cfw"}
    path = tmp_path / name
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    return str(path)


def test_shipped_splits_are_disjoint_and_train_has_two_ranges():
    cats = load_categories()
    train = cats.instances("cabinet", "train")
    explore = cats.instances("cabinet", "explore")
    test = cats.instances("cabinet", "test")
    assert train == list(range(0, 30)) + list(range(50, 270))
    assert explore == list(range(30, 40)) and test == list(range(40, 50))
    assert not set(train) & set(explore) and not set(train) & set(test)
    extra = cats.instances("cabinet", "extra")  # beyond the reference's 270, for scaling studies
    assert extra[0] == 270 and len(extra) > 1000
    assert not set(extra) & (set(train) | set(explore) | set(test))
    assert cats.novel("cfw") == [c for c in cats.categories
                                 if c not in ("cabinet", "faucet", "window")]


def test_a_split_may_be_one_range_or_a_list_of_ranges(tmp_path):
    cats = load_categories(_write(tmp_path, {"train": [[0, 3], [10, 12]], "explore": [3, 5],
                                             "test": [[5, 6]]}))
    assert cats.instances("kettle", "train") == [0, 1, 2, 10, 11]
    assert cats.instances("kettle", "explore") == [3, 4]
    assert cats.instances("kettle", "test") == [5]
    with pytest.raises(UnknownCategoryError):
        cats.instances("kettle", "holdout")
    with pytest.raises(UnknownCategoryError):
        cats.instances("spaceship", "train")


@pytest.mark.parametrize("splits, match", [
    ({"train": [[0, 30], [50, 270]], "explore": [30, 40], "test": [260, 280]},
     "instance 260 is in splits train and test"),
    ({"train": [[0, 10], [5, 12]], "explore": [30, 40], "test": [40, 50]},
     "instance 5 is in splits train and train"),
    ({"train": [0, 10], "explore": [9, 11], "test": [40, 50]},
     "instance 9 is in splits train and explore"),
])
def test_overlapping_splits_are_rejected(tmp_path, splits, match):
    with pytest.raises(ValueError, match=match):
        load_categories(_write(tmp_path, splits))


@pytest.mark.parametrize("bad", [[5, 5], [7, 3], [[0, 3], [4]], [[0, 1, 2]]])
def test_malformed_ranges_are_rejected(tmp_path, bad):
    with pytest.raises(ValueError, match="malformed range"):
        load_categories(_write(tmp_path, {"train": bad, "explore": [30, 40],
                                          "test": [40, 50]}))
