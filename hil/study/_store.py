"""Where a study lives: its Optuna RDB storage and ``open_study``.

SQLite by default, any SQLAlchemy URL for a study several machines share; a heartbeat fails the trials of a killed
run. ``open_study`` creates a study, or loads one and checks it was made with the same space and objective."""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hil.config import ConfigError

if TYPE_CHECKING:
    import optuna

HEARTBEAT_S = 30  # RDB heartbeat: a trial left RUNNING by a killed run is failed after GRACE_S
GRACE_S = 120


def storage_url(storage: str | None, out_dir: Path) -> str:
    if storage is None:
        return f"sqlite:///{(out_dir / 'tune.db').absolute()}"
    if "://" not in storage:
        raise ConfigError(f"storage={storage!r}: not a database URL (e.g. sqlite:///tune.db, "
                          "postgresql://user@host/db)")
    return storage


def rdb_storage(url: str) -> optuna.storages.RDBStorage:
    import optuna  # noqa: PLC0415  (heavy (Optuna, SQLAlchemy): loaded only when a study runs)
    import sqlalchemy.exc  # noqa: PLC0415  (heavy (Optuna, SQLAlchemy): loaded only when a study runs)

    kwargs: dict[str, Any] = {"connect_args": {"timeout": 60}} if url.startswith("sqlite") else {}
    try:
        with warnings.catch_warnings():  # the heartbeat is marked experimental
            warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
            return optuna.storages.RDBStorage(url, engine_kwargs=kwargs, heartbeat_interval=HEARTBEAT_S,
                                              grace_period=GRACE_S)
    except (sqlalchemy.exc.SQLAlchemyError, ImportError, ValueError) as exc:
        msg = " ".join(str(exc).split())
        raise ConfigError(f"storage={url!r}: cannot open: {msg[:200]}") from None


def open_study(rdb: Any, study_name: str, sampler: Any, direction: str | Sequence[str], *, meta: dict[str, Any],
               exists: bool, pruner: Any = None) -> optuna.Study:
    """Create the study, or load it (``exists``) and check it was made with the same ``meta`` (its user attributes:
    the space, the objective, ...); ConfigError naming ``resume`` if not. A new study gets ``meta`` stored."""
    import optuna  # noqa: PLC0415  (heavy (Optuna, SQLAlchemy): loaded only when a study runs)

    directions = [direction] if isinstance(direction, str) else list(direction)
    # the direction strings as the caller gives them: Optuna checks them itself
    st = optuna.create_study(storage=rdb, sampler=sampler, pruner=pruner, study_name=study_name,
                             directions=directions, load_if_exists=True)  # type: ignore[arg-type]
    for key, value in meta.items():
        if not exists:
            st.set_user_attr(key, value)
        elif st.user_attrs.get(key) != value:
            raise ConfigError(f"resume=True: study={study_name!r} was made with {key} {st.user_attrs.get(key)!r}, "
                              f"not {value!r}; choose another study name")
    return st
