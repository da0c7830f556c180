"""The test command's order (tests/conftest.py): every file named to start first is there, so that a renamed one
does not lose its place unseen."""

from tests.conftest import LONGEST_FIRST, REPO


def test_every_file_named_to_start_first_exists() -> None:
    missing = [path for path in LONGEST_FIRST if not (REPO / path).is_file()]
    assert not missing, f"tests/conftest.py LONGEST_FIRST names files that are not there: {missing}"
