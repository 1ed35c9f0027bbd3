"""The benchmark's test split holds no map the map-table farm trains on."""

import pytest

from eval.navigate.run import NavConfig, check_config
from precompute.maps.worlds import suite_worlds
from precompute.worlds.suites import SuiteError
from precompute.worlds.tasks import make_tasks, split_of


def test_forest_test_split_is_every_fifth_seed_from_seed():
    tasks = make_tasks("forest", 0.2, 4, seed=3, split="test")
    assert [t.task_id for t in tasks] == [5, 10, 15, 20]
    train = make_tasks("forest", 0.2, 3, seed=4, split="train")
    assert [t.task_id for t in train] == [4, 6, 7]


def test_barn_test_split_keeps_ids_divisible_by_five():
    ids = [t.task_id for t in make_tasks("barn", 0.2, 5, split="test")]
    assert len(ids) == 5 and all(i % 5 == 0 for i in ids)
    assert [t.task_id for t in make_tasks("barn", 0.2, 3, split="all")] == [0, 2, 4]  # the shipped half


def test_farm_train_maps_never_in_the_benchmark_test_split():
    keys = {w.key for w in suite_worlds("barn", 20, "train", seed=0, radius=0.2)}
    test_ids = {t.task_id for t in make_tasks("barn", 0.2, None, split="test")}
    assert keys and not keys & test_ids
    assert all(split_of(k) == "train" for k in keys)


def test_bad_split_and_empty_split_are_clear_errors():
    with pytest.raises(SuiteError, match="train split of gaps holds no task"):
        make_tasks("gaps", 0.2, None, split="train")
    with pytest.raises(ValueError, match="unknown split 'heldout'"):
        check_config(NavConfig(suite="forest", split="heldout"))


def test_clutter_suite_is_the_forest_corridor_denser():
    from precompute.worlds.suites import make_suite
    from precompute.worlds.tasks import CLUTTER

    tasks = make_tasks("clutter", 0.2, 3, split="test")
    assert [t.task_id for t in tasks] == [0, 5, 10] and {t.suite for t in tasks} == {"clutter"}
    lo, hi = CLUTTER["num_discs"]
    assert all(lo <= len(t.discs) <= hi and (t.discs[:, 2] == CLUTTER["disc_radius"]).all() for t in tasks)
    forest = make_tasks("forest", 0.2, 3, split="test")
    assert all(len(f.discs) < len(c.discs) for f, c in zip(forest, tasks))
    # split "all" keeps the forest's tasks of before the split existed: seeds seed..seed+count-1
    old = make_suite("forest", 4, seed=7, robot_radius=0.2)
    new = make_tasks("forest", 0.2, 4, seed=7)
    assert [t.task_id for t in new] == [7, 8, 9, 10]
    assert all((a.discs == b.discs).all() for a, b in zip(old, new))


def test_farm_builds_clutter_worlds_of_the_benchmark_density():
    from precompute.maps.worlds import world_of
    from precompute.worlds.tasks import CLUTTER

    w = world_of("clutter", 3, 0.2)
    assert w.source == "clutter:seed=3" and CLUTTER["num_discs"][0] <= len(w.discs) <= CLUTTER["num_discs"][1]
