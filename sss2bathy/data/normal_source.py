"""Where the SIREN's normal targets come from: ``data.normals`` (``conf/data/normals/``).

One nested config, chosen as a Hydra group (``data/normals=gt|cnn|none``)::

    normals:
      source: cnn          # gt (draped MBES) | cnn (a CNN's predictions) | none (sonar mask only)
      checkpoint: latest   # cnn: a .ckpt / .safetensors path, latest (newest CNN run of
                           #      runs_dir at this scale) or pretrained (the shipped CNN)
      runs_dir: ${paths.output_dir}/runs/cnn
      scale: ${oc.select:scale.name,null}
      window: null         # the CNN's windows; null = those stored in the checkpoint
      precision: fp32      # fp32 | bf16 inference
      overlap: null        # inference overlap in [0, 1); null = the training overlap

``source: gt`` and ``none`` take no other key. :meth:`NormalSource.coerce` checks the
whole block once (a bad value is one ``ValueError`` naming ``data.normals.<key>``, the
expected and the found value) and :meth:`NormalSource.resolve` turns ``latest`` and
``pretrained`` into the checkpoint file, once per run.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields, replace
from typing import Any

from sss2bathy.data.cnn_normals import check_overlap, check_precision, resolve_cnn_checkpoint
from sss2bathy.utils.checks import require_int, require_number

NORMAL_SOURCES = ("gt", "cnn", "none")
#: how errors name the block (a caller's aliases rename it, e.g. sss2bathy-map's cnn_checkpoint)
KEY = "data.normals"


def check_window(window: Mapping[str, Any] | None, key: str = f"{KEY}.window") -> dict | None:
    """The CNN's window settings as a plain dict (``None``: those stored in the checkpoint),
    its values checked: ``window_pings`` a positive integer, ``window_bins`` a positive
    integer or null (the lines' bins), ``overlap`` in [0, 1)."""
    if window is None:
        return None
    if not isinstance(window, Mapping):
        raise ValueError(f"{key}: expected a mapping or null, found {window!r}")
    window = {str(k): v for k, v in window.items()}
    if "window_pings" in window:
        require_int(f"{key}.window_pings", window["window_pings"])
    if window.get("window_bins") is not None:
        require_int(f"{key}.window_bins", window["window_bins"])
    if "overlap" in window:
        require_number(
            f"{key}.overlap", window["overlap"], lambda v: 0 <= v < 1, "a fraction in [0, 1)"
        )
    return window


@dataclass(frozen=True)
class NormalSource:
    """``data.normals``: the source of the normal targets and, for ``cnn``, the CNN's
    checkpoint and inference settings (module docstring)."""

    source: str = "gt"
    checkpoint: str | None = None
    runs_dir: str | None = None
    scale: str | None = None
    window: Mapping[str, Any] | None = None
    precision: str = "fp32"
    overlap: float | None = None

    def __post_init__(self) -> None:
        if self.source not in NORMAL_SOURCES:
            raise ValueError(
                f"{KEY}.source: expected one of {list(NORMAL_SOURCES)}, found {self.source!r}"
            )
        if self.source != "cnn":
            extra = [
                f.name
                for f in fields(self)
                if f.name != "source" and getattr(self, f.name) != f.default
            ]
            if extra:
                raise ValueError(
                    f"{KEY}.{extra[0]}: expected no CNN setting with source {self.source} "
                    f"(only with data/normals=cnn), found {getattr(self, extra[0])!r}"
                )
            return
        if not self.checkpoint:
            raise ValueError(
                f"{KEY}.checkpoint: expected a checkpoint path, 'latest' or 'pretrained' for "
                "source cnn, found none"
            )
        if str(self.checkpoint) == "latest" and not self.runs_dir:
            raise ValueError(
                f"{KEY}.runs_dir: expected the CNN runs folder for checkpoint latest, found none"
            )
        object.__setattr__(self, "checkpoint", str(self.checkpoint))
        object.__setattr__(self, "window", check_window(self.window))
        check_precision(self.precision, f"{KEY}.precision")
        object.__setattr__(self, "overlap", check_overlap(self.overlap, f"{KEY}.overlap"))

    @classmethod
    def coerce(cls, value: NormalSource | Mapping[str, Any] | str | None) -> NormalSource:
        """A :class:`NormalSource` from itself, a source name (``"gt"``), a mapping of its
        fields (``data.normals``) or ``None`` (``gt``); unknown keys are one error."""
        if value is None:
            return cls()
        if isinstance(value, cls):
            return value
        if isinstance(value, str):
            return cls(source=value)
        if not isinstance(value, Mapping):
            raise ValueError(
                f"{KEY}: expected a mapping of {[f.name for f in fields(cls)]} or one of "
                f"{list(NORMAL_SOURCES)}, found {value!r}"
            )
        names = {f.name for f in fields(cls)}
        given = {str(k): v for k, v in value.items()}
        unknown = sorted(set(given) - names)
        if unknown:
            raise ValueError(f"{KEY}.{unknown[0]}: expected one of {sorted(names)}, found it")
        return cls(**given)

    def resolve(self) -> NormalSource:
        """The same source with ``checkpoint`` the CNN file it names (``latest``: the newest
        CNN run of ``runs_dir`` at ``scale``; ``pretrained``: the shipped model), which must
        exist; unchanged for ``gt`` and ``none``."""
        if self.source != "cnn":
            return self
        path = resolve_cnn_checkpoint(
            self.checkpoint, self.runs_dir, self.scale, key=f"{KEY}.checkpoint"
        )
        return replace(self, checkpoint=str(path))
