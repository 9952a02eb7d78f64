"""Categories, instance splits and training combinations from ``config/categories.yaml``."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import yaml

from w2e_ros.paths import config_dir

SPLITS = ("train", "explore", "test", "extra")


class UnknownCategoryError(ValueError):
    """A category, combination or split name that the configuration does not define."""


@dataclass(frozen=True)
class CategoryConfig:
    categories: tuple[str, ...]
    splits: dict[str, tuple[tuple[int, int], ...]]  # half-open [start, stop) ranges
    combinations: dict[str, tuple[str, ...]]
    default_combination: str

    def check_category(self, category: str) -> str:
        if category not in self.categories:
            raise UnknownCategoryError(
                f"unknown category {category!r}; known: {', '.join(self.categories)}"
            )
        return category

    def instances(self, category: str, split: str) -> list[int]:
        """Instance ids of a category in a split (train / explore / test / extra)."""
        self.check_category(category)
        if split not in self.splits:
            raise UnknownCategoryError(
                f"unknown split {split!r}; known: {', '.join(self.splits)}")
        return [i for start, stop in self.splits[split] for i in range(start, stop)]

    def training_instances(self, category: str) -> list[int]:
        """Instances a model may train on: the train split and, where the file defines it,
        the extra split (never explored, never judged). Training data is filtered to these,
        so a collection of explore or test instances can never leak into a model."""
        extra = self.instances(category, "extra") if "extra" in self.splits else []
        return self.instances(category, "train") + extra

    def evaluation_instances(self, category: str, validate: bool = False,
                             explored: int = 10) -> list[int]:
        """Instances a few-shot model is judged on: the TEST split, or with ``validate`` the
        explore-split instances after the first ``explored`` (never explored, never test), so
        that settings can be chosen without looking at the test instances."""
        if not validate:
            return self.instances(category, "test")
        held_out = self.instances(category, "explore")[explored:]
        if not held_out:
            raise ValueError(f"validation needs explore instances of {category} beyond the "
                             f"{explored} explored ones; explore fewer objects")
        return held_out

    def combination(self, name: str | None = None) -> tuple[str, ...]:
        """Training categories of a combination; the first is C_aff, all three are C_sim."""
        name = name or self.default_combination
        if name not in self.combinations:
            raise UnknownCategoryError(
                f"unknown combination {name!r}; known: {', '.join(self.combinations)}"
            )
        return self.combinations[name]

    def novel(self, name: str | None = None) -> list[str]:
        """The categories a combination never trains on (11 of the 14)."""
        train = set(self.combination(name))
        return [c for c in self.categories if c not in train]


def _parse(path: Path) -> CategoryConfig:
    raw = yaml.safe_load(path.read_text())
    cats = tuple(raw["categories"])
    combos = {k: tuple(v) for k, v in raw["combinations"].items()}
    for name, members in combos.items():
        unknown = [c for c in members if c not in cats]
        if unknown or len(members) != 3:
            raise ValueError(f"{path}: combination {name} is malformed: {members}")
    splits = {k: _ranges(v, path, k) for k, v in raw["splits"].items()}
    seen: dict[int, str] = {}
    for name, ranges in splits.items():
        for start, stop in ranges:
            for i in range(start, stop):
                if i in seen:
                    raise ValueError(f"{path}: instance {i} is in splits {seen[i]} and {name}")
                seen[i] = name
    return CategoryConfig(cats, splits, combos, raw["default_combination"])


def _ranges(value: list, path: Path, split: str) -> tuple[tuple[int, int], ...]:
    """``[a, b]`` or ``[[a, b], [c, d], ...]`` -> ((a, b), ...), each checked."""
    items = value if value and isinstance(value[0], list) else [value]
    out = []
    for item in items:
        if len(item) != 2 or int(item[0]) >= int(item[1]):
            raise ValueError(f"{path}: split {split} has a malformed range {item}")
        out.append((int(item[0]), int(item[1])))
    return tuple(out)


@lru_cache(maxsize=4)
def load_categories(path: str | None = None) -> CategoryConfig:
    """Parse the category file once per process (``path`` overrides the shipped file)."""
    return _parse(Path(path) if path else config_dir() / "categories.yaml")
