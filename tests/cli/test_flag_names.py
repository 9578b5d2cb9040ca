"""Library errors name API parameters; the CLI words them as its flags (cli.common.FLAG_NAMES)."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from cli.common import one_line
from streamer.errors import BudgetError
from tiler.encoding import quantise
from tiler.errors import SourceError, StoreError, StoreExistsError


def _errors():
    yield (
        "level",
        StoreError(
            "{level_param} must be in 0..{k} for this store, got {level}",
            params={"level_param": "level"},
            k=5,
            level=7,
        ),
        "level must be in 0..5 for this store, got 7",
        "--level must be in 0..5 for this store, got 7",
    )
    yield (
        "overwrite",
        StoreExistsError(
            "{url!r} already holds a finished store; tile with {overwrite} to replace it.",
            params={"overwrite": "overwrite=True"},
            url="s.zarr",
        ),
        "tile with overwrite=True to replace it",
        "tile with --overwrite to replace it",
    )
    yield (
        "budget",
        BudgetError(
            "the budget is {budget}; raise {budget_mb} or the error threshold {tau}",
            params={"budget_mb": "budget_mb", "tau": "tau"},
            budget="1 MiB",
        ),
        "1 MiB; raise budget_mb or the error threshold tau",
        "1 MiB; raise --budget-mb or the error threshold --tau",
    )

    from tiler.resume import check_same_job

    try:  # a rerun of another job (was "tile with overwrite", the API's word, in the CLI too)
        check_same_job("s.zarr", {"block_size": 33}, {"block_size": 65})
    except StoreError as exc:
        mismatch = exc
    yield (
        "job-mismatch",
        mismatch,
        "block_size: store has 33, this run has 65); rerun with the original source and "
        "settings to finish it, or tile with overwrite=True to start again.",
        "or tile with --overwrite to start again.",
    )

    from streamer.errors import LoadError
    from streamer.waits import MORE_TIME

    yield (
        "more-time",
        LoadError(
            "warm-up did not finish within {limit:.1f} s ({state}): check the store's "
            "server{more_time}",
            params=MORE_TIME,
            limit=30.0,
            state="{4 read(s) running}",  # braces in a value are kept as they are
        ),
        "s ({4 read(s) running}): check the store's server, or allow more time (warm_up's",
        "s ({4 read(s) running}): check the store's server",  # the CLI has no such option
    )


@pytest.mark.parametrize(
    ("error", "api", "cli"), [e[1:] for e in _errors()], ids=[e[0] for e in _errors()]
)
def test_library_words_parameters_the_cli_words_flags(error, api, cli):
    assert api in str(error) and "--" not in str(error)
    assert cli in one_line(error)
    back = pickle.loads(pickle.dumps(error))  # through a worker process
    assert type(back) is type(error) and str(back) == str(error) and cli in one_line(back)


def test_quantise_overflow_names_the_value_and_the_flag():
    with pytest.raises(SourceError) as e:
        quantise(np.array([1e9]), 0.001)
    assert "precision 0.001 is too fine for values up to 1e+09" in str(e.value)
    assert "choose a coarser precision." in str(e.value)
    assert "choose a coarser --precision." in one_line(e.value)


def test_plain_library_errors_are_unchanged():
    e = SourceError("band 3 does not exist")
    assert str(e) == one_line(e) == "band 3 does not exist"
    assert str(pickle.loads(pickle.dumps(e))) == "band 3 does not exist"


def test_a_wait_timeout_offers_the_cli_no_option_it_lacks():
    from streamer.errors import LoadError
    from streamer.waits import MORE_TIME

    err = LoadError("timed out ({state}): check the server{more_time}", params=MORE_TIME, state="x")
    assert str(err).endswith("or allow more time (warm_up's timeout_s, wait_timeout_s)")
    assert one_line(err).endswith("timed out (x): check the server")
