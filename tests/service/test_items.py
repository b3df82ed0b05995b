"""What a client submits is checked by its kind's own loader, with the command line's one-line error naming the
submitted file (hil.service.check_item; docs/service.md, "Items")."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from hil.config import load_session
from hil.service import ItemError, check_item

REPO = Path(__file__).resolve().parents[2]
SESSION = REPO / "profiles" / "sessions" / "swing-1deg-1hz-eso.yaml"


def as_submitted() -> dict:  # type: ignore[type-arg]
    """The session as `hil run --bench` sends it: loaded, its includes inline."""
    return load_session(SESSION).model_dump(mode="json", exclude_none=True)


def test_a_session_as_loaded_stands_on_its_own() -> None:
    item = check_item("session", "mine/swing.yaml", yaml.safe_dump(as_submitted()))
    assert (item.kind, item.name) == ("session", "swing-1deg-1hz-eso")
    assert item.config == load_session(SESSION)


def test_a_bad_field_is_the_command_line_s_one_line_naming_the_submitted_file() -> None:
    data = as_submitted()
    data["duration_s"] = -1
    with pytest.raises(ItemError) as exc:
        check_item("session", "mine/swing.yaml", yaml.safe_dump(data))
    message = str(exc.value)
    assert message.startswith("mine/swing.yaml: duration_s:") and "\n" not in message
    assert "hil-item-" not in message  # never a path of the service's


def test_a_file_that_leans_on_the_client_s_other_files_is_refused_by_name() -> None:
    text = SESSION.read_text()  # its controller, profile and limits are paths relative to it
    with pytest.raises(ItemError) as exc:
        check_item("session", "swing.yaml", text)
    assert "hil-item-" not in str(exc.value) and "controllers/eso.yaml" in str(exc.value), exc.value


@pytest.mark.parametrize(("kind", "name", "body", "message"), [
    ("plot", "a.yaml", "", r"^kind='plot': not session, ident, campaign$"),
    ("session", "a.txt", "", r"^a.txt: not a YAML file \(.yaml or .yml\)$"),
    ("session", "a.yaml", "x" * (1 << 20 + 1), r"^a.yaml: 2097152 bytes, more than the 1048576 an item may have$"),
    ("campaign", "c.yaml", "name: [", r"^c.yaml: "),
])
def test_what_is_not_an_item_is_refused(kind: str, name: str, body: str, message: str) -> None:
    with pytest.raises(ItemError, match=message):
        check_item(kind, name, body)
