"""Which interactions train which head: the method's categories (``w2e``: C_aff trains the
affordance head, all of C_sim the similarity head; ``where2act`` and ``fulldata``: the
affordance head alone) and the train-split interactions of them."""

from __future__ import annotations

from pathlib import Path

from w2e_ros.core.dataset.categories import load_categories
from w2e_ros.core.dataset.interactions import InteractionData
from w2e_ros.core.model.config import METHODS


def method_categories(method: str, combo: str) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(categories training the affordance head, categories training the similarity head)."""
    cats = load_categories()
    members = cats.combination(combo)
    if method == "w2e":
        return (members[0],), tuple(members)
    if method == "where2act":
        return tuple(members), ()
    if method == "fulldata":
        return tuple(cats.categories), ()
    raise ValueError(f"unknown method {method!r}; known: {', '.join(METHODS)}")


def retarget(meta: dict, combo: str, source: str = "the model") -> dict:
    """A w2e checkpoint's metadata for another combination with the same C_aff.

    The affordance head of a w2e model trains on C_aff alone, so cfw / csr (cabinet) and
    tfr / tsw (table) can share one; what differs is the similarity, which the caller then
    fits on the new combination's categories (``w2e calibrate --combo``)."""
    method, own = str(meta.get("method", "w2e")), str(meta.get("combo", "cfw"))
    if combo == own:
        return meta
    if method != "w2e":
        raise ValueError(f"{source}: only w2e models can be given another combination (a "
                         f"{method} model's affordance head trains on every category of {own})")
    have, want = method_categories(method, own)[0][0], method_categories(method, combo)[0][0]
    if have != want:
        raise ValueError(f"{source}: trained for {own} (C_aff {have}); {combo} has C_aff "
                         f"{want}: train a model for it (w2e train --combo {combo})")
    return {**meta, "combo": combo, "retargeted_from": own}


def load_training_data(data_dir: str | Path, method: str, combo: str, primitive: str,
                       include_invalid: bool = True) -> InteractionData:
    """The training interactions (train and extra splits) of one primitive on the method's
    training categories."""
    return load_training_data_from(InteractionData.load(data_dir), method, combo, primitive,
                                   include_invalid, source=str(data_dir))


def load_training_data_from(data: InteractionData, method: str, combo: str, primitive: str,
                            include_invalid: bool = True, source: str = "the collection"
                            ) -> InteractionData:
    """:func:`load_training_data` on a collection already in memory."""
    aff, sim = method_categories(method, combo)
    cats = tuple(dict.fromkeys(aff + sim))
    split = load_categories().training_instances(cats[0])
    sel = data.select(primitive=primitive, categories=cats, instances=split,
                      valid_only=not include_invalid)
    if sel.num_interactions == 0:
        raise ValueError(f"{source}: no {primitive} interactions on train instances of "
                         f"{', '.join(cats)}")
    return sel
