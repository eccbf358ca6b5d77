"""Shared start-up for the entry points: project root, config path, run records, and
one-line user errors.

A user error (a bad file, a bad config value, a missing checkpoint, a typo'd override) ends
an entry point with ONE line on stderr, ``error: <what happened>``, and exit status 2
(:data:`USER_ERROR_EXIT`); ``--trace`` on the command line or ``HYDRA_FULL_ERROR=1`` shows
the traceback instead. Hydra entry points use :func:`hydra_entry` in place of
``@hydra.main``; plain ``argparse`` ones wrap their body in :func:`user_errors`.

``--help`` prints a short :class:`CliHelp` (usage line, main keys, examples);
``--hydra-help`` Hydra's full help. Checks that need only the config (keys, group options,
CRS values, a writable output folder, the entry point's own) run before Hydra makes the run
folder; a run that fails at start-up anyway leaves no empty run folder. The composed config
goes to ``config.yaml`` in the run folder, not to the console.
"""

from __future__ import annotations

import difflib
import errno
import functools
import itertools
import json
import logging
import os
import re
import shutil
import subprocess
import sys
import textwrap
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from sss2bathy.utils.atomic import atomic_write_text

log = logging.getLogger("sss2bathy")


def project_root() -> Path:
    """The project root: ``$SSS2BATHY_ROOT``, else the checkout this package lives in, else cwd."""
    env = os.environ.get("SSS2BATHY_ROOT")
    if env:
        return Path(env).resolve()
    here = Path(__file__).resolve().parents[2]
    if (here / "conf").is_dir() and (here / "pyproject.toml").is_file():
        return here
    return Path.cwd().resolve()


def config_dir() -> str:
    """Absolute path of ``conf/`` (editable installs and checkouts)."""
    path = project_root() / "conf"
    if not path.is_dir():
        raise FileNotFoundError(
            f"conf/ not found under {path.parent}; run from the project checkout or set "
            "SSS2BATHY_ROOT to it"
        )
    return str(path)


def setup_environment() -> None:
    """Set ``SSS2BATHY_ROOT`` so ``conf/paths`` resolves, keep glibc from re-faulting the
    memory of large tensors (:func:`sss2bathy.utils.alloc.tune_allocator`; opt out with
    ``SSS2BATHY_MALLOC=default``) and put the thread policy's environment defaults in place
    (:func:`sss2bathy.utils.threads.set_env_defaults`, already done when ``sss2bathy.cli``
    was imported); call before ``@hydra.main``."""
    from sss2bathy.utils.alloc import tune_allocator
    from sss2bathy.utils.threads import set_env_defaults

    set_env_defaults()
    os.environ.setdefault("SSS2BATHY_ROOT", str(project_root()))
    if TRACE_FLAG in sys.argv[1:]:
        sys.argv = [a for a in sys.argv if a != TRACE_FLAG]
        os.environ[TRACE_ENV] = "1"
        os.environ["HYDRA_FULL_ERROR"] = "1"  # Hydra's own errors with their trace too
    tune_allocator()


# ----------------------------------------------------------------------------- user errors
TRACE_FLAG = "--trace"
TRACE_ENV = "SSS2BATHY_TRACE"
USER_ERROR_EXIT = 2
HELP_FLAGS = ("-h", "--help")
HYDRA_HELP_FLAG = "--hydra-help"

#: how a failed start's run folder may look and still be removed: Hydra's own records, the
#: job's log and the config dump (:func:`log_config`), nothing the run made
_START_FILES = ("config.yaml",)
_START_SUFFIXES = (".log",)


def show_traceback() -> bool:
    """``--trace`` was given, or ``HYDRA_FULL_ERROR=1``: let errors raise with their trace."""
    return os.environ.get(TRACE_ENV) == "1" or os.environ.get("HYDRA_FULL_ERROR") == "1"


def user_error_types() -> tuple[type[BaseException], ...]:
    """Exceptions that are the user's input, not a bug: reported in one line.

    ``OSError`` covers a missing file, a folder without write permission, a read-only file
    system and a full disk (:func:`os_error_message`); other ``OSError`` s name their file."""
    from sss2bathy.config_validation import ConfigError
    from sss2bathy.survey import SurveyFormatError

    return (SurveyFormatError, ConfigError, ValueError, OSError)


#: ``OSError`` numbers that are the user's environment (a path, its permissions, its disk)
USER_OS_ERRNOS = frozenset(
    {
        errno.ENOENT,
        errno.ENOTDIR,
        errno.EISDIR,
        errno.EACCES,
        errno.EPERM,
        errno.EROFS,
        errno.ENOSPC,
        errno.EDQUOT,
        errno.ENAMETOOLONG,
    }
)


def is_user_error(err: BaseException) -> bool:
    """A user error of :func:`user_error_types`; of the ``OSError`` s only a missing file
    and those of :data:`USER_OS_ERRNOS` (other I/O failures keep their traceback)."""
    if not isinstance(err, OSError) or isinstance(err, FileNotFoundError | PermissionError):
        return True
    return err.errno in USER_OS_ERRNOS or _disk_full(err)


def one_line(message: str) -> str:
    """``message`` on one line (line breaks and runs of blanks become single blanks)."""
    return re.sub(r"\s+", " ", str(message)).strip()


def rename_keys(message: str, aliases: Mapping[str, str] | None) -> str:
    """``message`` with each config key prefix of ``aliases`` (``{"data.survey.":
    "survey."}``) spelled as the entry point spells it; only whole key prefixes (not
    ``paths.data.survey.x``)."""
    for old, new in (aliases or {}).items():
        message = re.sub(rf"(?<![\w.]){re.escape(old)}", new, message)
    return message


class RenameKeys(logging.Filter):
    """A log handler filter spelling config keys as the entry point does
    (:func:`rename_keys`), so warnings name the keys a user of that command types."""

    def __init__(self, aliases: Mapping[str, str]) -> None:
        super().__init__()
        self.aliases = dict(aliases)

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        renamed = rename_keys(message, self.aliases)
        if renamed != message:
            record.msg, record.args = renamed, None
        return True


def _rename_keys_in_logs(aliases: Mapping[str, str] | None) -> None:
    if not aliases:
        return
    for handler in logging.getLogger().handlers:
        if not any(isinstance(f, RenameKeys) for f in handler.filters):
            handler.addFilter(RenameKeys(aliases))


def _human_bytes(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if n < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} TiB"


def _existing_parent(path: Path) -> Path:
    path = Path(path).absolute()
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def _disk_full(err: OSError) -> bool:
    # rasterio's and h5py's errors carry GDAL's / HDF5's text, not an errno
    return err.errno in (errno.ENOSPC, errno.EDQUOT) or "No space left on device" in str(err)


def os_error_message(err: OSError, folders: Sequence[str | Path] = ()) -> str:
    """One line for an ``OSError`` of the user's environment, naming its path: no
    permission, a read-only file system, a full disk (with the free space), a missing
    file. ``folders``: where the run writes (its run folder, ``paths.data_dir``), named
    with their free space when a full disk's error names no file (a failed ``write``)."""
    path = err.filename if err.filename is not None else None
    other = f" -> {err.filename2}" if getattr(err, "filename2", None) else ""
    if _disk_full(err):
        places = [Path(str(path))] if path is not None else [Path(str(f)) for f in folders]
        free = []
        for place in dict.fromkeys(places):
            try:
                space = _human_bytes(shutil.disk_usage(_existing_parent(place)).free)
            except OSError:
                space = "unknown"
            free.append(f"{space} free at {place}" if path is None else f"{space} free there")
        if path is not None:
            where = f"{path}{other}: no space left on its disk"
        elif err.errno is None:  # a library's error: its own text names the file
            where = one_line(str(err))
        else:
            where = "no space left on the disk while writing"
        return (
            f"{where} ({'; '.join(free) or 'free space unknown'}); free some space or point "
            "paths.output_dir / paths.data_dir at another disk"
        )
    path = "?" if path is None else path
    if err.errno == errno.EROFS:
        return (
            f"{path}{other}: read-only file system; point paths.output_dir / paths.data_dir "
            "at a writable folder"
        )
    if isinstance(err, PermissionError) or err.errno in (errno.EACCES, errno.EPERM):
        return (
            f"{path}{other}: permission denied (a read-only folder?); point "
            "paths.output_dir / paths.data_dir at a writable folder"
        )
    if err.filename is None:
        return str(err) or type(err).__name__
    reason = err.strerror or str(err) or type(err).__name__
    return f"{path}{other}: {reason}"


def error_message(err: BaseException, folders: Sequence[str | Path] = ()) -> str:
    """The one-line text of a user error (an ``OSError`` by :func:`os_error_message`)."""
    if isinstance(err, OSError) and (err.errno is not None or _disk_full(err)):
        return os_error_message(err, folders)
    return str(err) or type(err).__name__


def _write_folders(cfg: Any) -> list[str]:
    """Where a Hydra task writes: its run folder and ``paths.data_dir`` (what exists)."""
    folders = [str(p) for p in (_hydra_run_dir(),) if p is not None]
    if isinstance(cfg, DictConfig):
        try:
            data = OmegaConf.select(cfg, "paths.data_dir", default=None)
        except Exception:
            data = None
        if data is not None:
            folders.append(str(data))
    return folders


def report_user_error(message: str, aliases: Mapping[str, str] | None = None) -> None:
    """Print ``error: <message>`` as one line on stderr (config keys renamed by
    ``aliases``, :func:`rename_keys`) and exit with status 2."""
    print(f"error: {one_line(rename_keys(message, aliases))}", file=sys.stderr, flush=True)
    raise SystemExit(USER_ERROR_EXIT)


def _remove_failed_run_dir(cfg: Any = None) -> None:
    """Inside a single Hydra run: remove its run folder when it holds nothing the run made
    (Hydra's ``.hydra/``, the job's log, ``config.yaml``, empty folders), so a run that
    failed at start-up leaves no empty run folder behind; then the folders above it that
    are left empty, up to ``cfg.paths.output_dir`` (kept)."""
    try:
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode

        hc = HydraConfig.get()
        if hc.mode != RunMode.RUN:
            return
        folder = Path(hc.runtime.output_dir)
    except (ValueError, ImportError, AttributeError):
        return
    if not folder.is_dir():
        return
    for path in folder.rglob("*"):
        rel = path.relative_to(folder)
        if path.is_dir() or rel.parts[0] == ".hydra":
            continue
        if len(rel.parts) == 1 and (rel.name in _START_FILES or rel.suffix in _START_SUFFIXES):
            continue
        return  # the run made something: keep its folder
    shutil.rmtree(folder, ignore_errors=True)
    try:
        top = OmegaConf.select(cfg, "paths.output_dir", default=None) if cfg is not None else None
    except Exception:
        top = None
    if top is None:
        return
    top = Path(str(top)).absolute()
    parent = folder.absolute().parent
    while parent != top and top in parent.parents:
        try:
            parent.rmdir()  # only when empty (runs/<task>/ made for this run)
        except OSError:
            break
        parent = parent.parent


def apply_threads(cfg: Any) -> None:
    """The thread policy for a run of ``cfg`` (:func:`sss2bathy.utils.threads.
    apply_thread_policy` with its ``torch_threads``), announced in one INFO line."""
    from sss2bathy.utils.threads import apply_thread_policy

    value = cfg.get("torch_threads") if isinstance(cfg, DictConfig) else None
    if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
        return  # not a count: the task's validate_config reports it in one line
    apply_thread_policy(value)


def with_thread_policy(task: Callable[[DictConfig], Any]) -> Callable[[DictConfig], Any]:
    """``task`` starting with :func:`apply_threads` of its config."""

    @functools.wraps(task)
    def run(cfg: DictConfig) -> Any:
        apply_threads(cfg)
        return task(cfg)

    return run


def user_errors(
    fn: Callable[..., Any], aliases: Mapping[str, str] | None = None
) -> Callable[..., Any]:
    """Wrap an entry point: user errors (see :func:`user_error_types`) become one line on
    stderr (config keys renamed by ``aliases``) and exit status 2, unless
    :func:`show_traceback`; a Hydra run folder left with nothing in it is removed."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        _rename_keys_in_logs(aliases)
        try:
            return fn(*args, **kwargs)
        except user_error_types() as err:
            if show_traceback() or not is_user_error(err):
                raise
            cfg = args[0] if args else None
            message = error_message(err, _write_folders(cfg))
            _remove_failed_run_dir(cfg if isinstance(cfg, DictConfig) else None)
            report_user_error(message, aliases)

    return wrapper


def _suggest(word: str, options: Sequence[str]) -> str:
    close = difflib.get_close_matches(word, list(options), n=3, cutoff=0.6)
    return f"; did you mean {' or '.join(repr(c) for c in close)}?" if close else ""


def _keys_named(cfg: DictConfig, leaf: str, depth: int = 3, prefix: str = "") -> list[str]:
    """Full names of the keys called ``leaf`` at most ``depth`` levels down (values not
    resolved)."""
    found = []
    for key in cfg.keys():
        name = f"{prefix}{key}"
        if str(key) == leaf:
            found.append(name)
        node = cfg._get_node(key)
        if depth > 1 and isinstance(node, DictConfig) and not node._is_missing():
            try:
                found += _keys_named(node, leaf, depth - 1, f"{name}.")
            except Exception:  # an interpolated node: not searched
                continue
    return found


def _compose(config_name: str, overrides: list[str]) -> tuple[DictConfig | None, Exception | None]:
    """``config_name`` composed with ``overrides`` as Hydra will (no ``hydra`` node)."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=config_dir(), version_base="1.3"):
            return compose(config_name, overrides=overrides), None
    except (HydraException, OmegaConfBaseException, ValueError) as err:
        return None, err
    finally:
        GlobalHydra.instance().clear()


def _override_problem(config_name: str, overrides: list[str]) -> str | None:
    """Compose ``config_name`` with ``overrides`` as Hydra will; the one-line reason it
    fails (with a "did you mean" where a close key or option exists), else ``None``."""
    return _compose_checked(config_name, overrides)[1]


def _compose_checked(
    config_name: str, overrides: list[str]
) -> tuple[DictConfig | None, str | None]:
    """``(composed config, None)``, or ``(None, the one-line reason it fails)``."""
    from hydra.errors import MissingConfigException

    cfg, err = _compose(config_name, overrides)
    if err is None:
        return cfg, None
    text = one_line(str(err).replace("Set the environment variable HYDRA_FULL_ERROR=1", ""))
    if isinstance(err, MissingConfigException) and err.missing_cfg_file:
        name = str(err.missing_cfg_file).rsplit("/", 1)[-1]
        return None, one_line(str(err).splitlines()[0]) + _suggest(name, err.options or [])
    match = re.search(r"Could not override '([^']+)'", text)
    if match:
        key = match.group(1)
        parent, _, leaf = key.rpartition(".")
        rest = [o for o in overrides if o.split("=", 1)[0].lstrip("+~") != key]
        base, _ = _compose(config_name, rest)
        options: list[str] = []
        hint = ""
        if base is not None:
            node = OmegaConf.select(base, parent) if parent else base
            if isinstance(node, DictConfig):
                options = [str(k) for k in node.keys()]
            hint = _suggest(leaf, options)
            if not hint:  # the key exists deeper down: `crs=` for `survey.crs=`
                deeper = [k for k in _keys_named(base, leaf) if k != key]
                if deeper:
                    hint = f"; did you mean {' or '.join(repr(k) for k in deeper[:3])}?"
        return None, f"unknown config key '{key}'{hint} (to add a new key: +{key}=...)"
    return None, text


# ----------------------------------------------------------------------------- start-up checks
#: config nodes whose ``crs`` / ``*_crs`` keys are checked before a run starts
CRS_NODES = ("survey", "data.survey")


def check_crs_keys(cfg: DictConfig) -> None:
    """Every ``crs`` / ``*_crs`` key of the survey nodes (:data:`CRS_NODES`) names a CRS
    pyproj knows, else ``ValueError`` naming the key, the expected and the found value."""
    from pyproj import CRS
    from pyproj.exceptions import CRSError

    for prefix in CRS_NODES:
        node = OmegaConf.select(cfg, prefix, default=None, throw_on_resolution_failure=False)
        if not isinstance(node, DictConfig):
            continue
        for key in node.keys():
            key = str(key)
            if key != "crs" and not key.endswith("_crs"):
                continue
            try:
                value = node.get(key)
            except Exception:  # an interpolation that does not resolve here: checked later
                continue
            if value is None or not isinstance(value, str | int):
                continue
            try:
                CRS.from_user_input(value)
            except CRSError:
                raise ValueError(
                    f"config key '{prefix}.{key}': expected a coordinate reference system "
                    f"pyproj knows (e.g. EPSG:32633, or null to take the file's), found "
                    f"{value!r}"
                ) from None


def check_writable(cfg: DictConfig, keys: Sequence[str] = ("paths.output_dir",)) -> None:
    """Each folder of ``keys`` exists as a writable folder or can be made (its nearest
    existing parent is writable), else ``PermissionError`` naming it."""
    for key in keys:
        try:
            value = OmegaConf.select(cfg, key, default=None)
        except Exception:
            continue
        if value is None:
            continue
        parent = _existing_parent(Path(str(value)).expanduser())
        if not os.access(parent, os.W_OK):
            code = errno.EROFS if _read_only_fs(parent) else errno.EACCES
            raise PermissionError(code, os.strerror(code), str(parent))


def _read_only_fs(path: Path) -> bool:
    try:
        return bool(os.statvfs(path).f_flag & os.ST_RDONLY)
    except (OSError, AttributeError):
        return False


def startup_checks(cfg: DictConfig, check: Callable[[DictConfig], None] | None = None) -> None:
    """What every Hydra entry point checks on the composed config before Hydra makes the
    run folder: the CRS keys, a writable ``paths.output_dir``, then the entry point's own
    ``check``."""
    check_crs_keys(cfg)
    check_writable(cfg)
    if check is not None:
        check(cfg)


# ----------------------------------------------------------------------------- help
@dataclass(frozen=True)
class CliHelp:
    """What ``--help`` prints: a usage line, a sentence, the main keys and examples.

    Args:
        prog: the command (``sss2bathy-map``).
        usage: the arguments after ``prog`` on the usage line.
        summary: one sentence (wrapped).
        keys: ``(key, what it is)`` of the main keys (short).
        examples: whole command lines.
        hydra: a Hydra entry point: the lines on ``--trace``, ``--hydra-help`` and
            ``--cfg job`` follow.
    """

    prog: str
    usage: str
    summary: str
    keys: Sequence[tuple[str, str]] = ()
    examples: Sequence[str] = ()
    hydra: bool = True

    def text(self, width: int = 88) -> str:
        lines = [f"usage: {self.prog} {self.usage}", ""]
        lines += textwrap.wrap(self.summary, width)
        if self.keys:
            lines += ["", "main keys:"]
            col = min(26, max(len(k) for k, _ in self.keys) + 2)
            for key, what in self.keys:
                body = textwrap.wrap(what, width - col - 2) or [""]
                first = f"  {key:<{col}}" if len(key) < col else f"  {key}\n  {'':<{col}}"
                lines.append(first + body[0])
                lines += [f"  {'':<{col}}{b}" for b in body[1:]]
        if self.examples:
            lines += ["", "examples:"] + [f"  {e}" for e in self.examples]
        if self.hydra:
            lines += [
                "",
                "options:",
                "  --trace        show the traceback of an error instead of one line",
                "  --cfg job      print the composed config and exit",
                "  --hydra-help   every config group and key (Hydra's full help)",
            ]
        return "\n".join(lines) + "\n"


def _group_options(group: str) -> list[str]:
    folder = Path(config_dir()) / group
    return sorted(p.stem for p in folder.glob("*.yaml")) if folder.is_dir() else []


def collapse_series(names: list[str], at_least: int = 3) -> list[str]:
    """Sorted ``names`` with each run of ``at_least`` or more that differ only in a last
    letter (``x_a, x_b, ..., x_l``) shown as one ``x_<a-l>``, so a help stays short.

    >>> collapse_series(["p_a", "p_b", "p_c", "p_base", "q"])
    ['p_<a-c>', 'p_base', 'q']
    """
    by_prefix: dict[str, set[int]] = {}
    for name in names:
        m = re.fullmatch(r"(.*_)([a-z])", name)
        if m:
            by_prefix.setdefault(m[1], set()).add(ord(m[2]))
    series: dict[str, str] = {}
    for prefix, codes in by_prefix.items():
        # consecutive letters share code - rank
        for _, run in itertools.groupby(enumerate(sorted(codes)), lambda t: t[1] - t[0]):
            letters = [chr(code) for _, code in run]
            if len(letters) >= at_least:
                label = f"{prefix}<{letters[0]}-{letters[-1]}>"
                series.update({prefix + c: label for c in letters})
    return list(dict.fromkeys(series.get(name, name) for name in sorted(names)))


def default_help(config_name: str, doc: str | None) -> CliHelp:
    """A :class:`CliHelp` from an entry point's module docstring (its first line and its
    ``sss2bathy-...`` example lines) and its config's groups (``conf/<config_name>.yaml``)."""
    prog = f"sss2bathy-{config_name}"
    text = (doc or "").strip()
    first = text.split("\n\n", 1)[0].replace("\n", " ")
    summary = re.sub(r"^``[^`]+``:\s*", "", first)
    examples = [ln.strip() for ln in text.splitlines() if ln.strip().startswith("sss2bathy-")]
    keys: list[tuple[str, str]] = []
    try:
        defaults = OmegaConf.load(Path(config_dir()) / f"{config_name}.yaml").get("defaults")
    except OSError:
        defaults = None
    for entry in defaults or []:
        if not isinstance(entry, DictConfig):
            continue
        for group, value in entry.items():
            group = str(group).split("@", 1)[0].removeprefix("optional ")
            if group in ("hydra", "paths", "extras", "debug", "hparams_search", "_self_"):
                continue
            options = _group_options(group)
            if options:
                shown = ", ".join(collapse_series(options))
                keys.append((f"{group}=NAME", f"one of {shown} (default {value or 'none'})"))
    keys.append(("KEY=VALUE", "any key of the composed config (see --cfg job)"))
    return CliHelp(prog, "[KEY=VALUE ...] [-m] [--trace] [--hydra-help]", summary, keys, examples)


def _hydra_full_help(hydra_main: Callable[[], Any]) -> None:
    """``--hydra-help``: Hydra's help of the app (config groups and the composed config),
    then Hydra's own options."""
    argv = list(sys.argv)
    try:
        for flag in ("--help", HYDRA_HELP_FLAG):
            sys.argv = [argv[0], *(flag if a == HYDRA_HELP_FLAG else a for a in argv[1:])]
            try:
                hydra_main()
            except SystemExit as done:
                if done.code not in (0, None):
                    raise
    finally:
        sys.argv = argv
    raise SystemExit(0)


def hydra_entry(
    config_name: str,
    help: CliHelp | None = None,
    check: Callable[[DictConfig], None] | None = None,
    aliases: Mapping[str, str] | None = None,
) -> Callable[[Callable[[DictConfig], Any]], Callable[[], Any]]:
    """``@hydra.main`` for this project's entry points, with short help and one-line user
    errors.

    ``--help`` / ``-h`` print ``help`` (default :func:`default_help`); ``--hydra-help``
    prints Hydra's full help. Before Hydra runs (and makes the run folder), a single run's
    overrides are composed once so that a typo'd key or group option is reported in one
    line with a "did you mean", and :func:`startup_checks` (with the entry point's own
    ``check``) run on the composed config. Inside the task, user errors are one line too
    (:func:`user_errors`); the task starts with the thread policy (:func:`apply_threads`).
    ``aliases`` rename config keys in every message
    (:func:`rename_keys`), for an entry point whose keys sit elsewhere than in the config
    its errors come from.
    """
    import hydra

    def decorate(task: Callable[[DictConfig], Any]) -> Callable[[], Any]:
        hydra_main = hydra.main(
            version_base="1.3", config_path=config_dir(), config_name=config_name
        )(user_errors(with_thread_policy(task), aliases))
        text = help or default_help(config_name, sys.modules[task.__module__].__doc__)

        @functools.wraps(task)
        def entry(cfg_passthrough: DictConfig | None = None) -> Any:
            if cfg_passthrough is not None:
                return hydra_main(cfg_passthrough)
            args = sys.argv[1:]
            if any(a in HELP_FLAGS for a in args):
                print(text.text(), end="", flush=True)
                raise SystemExit(0)
            if HYDRA_HELP_FLAG in args:
                _hydra_full_help(hydra_main)
            plain = all(not a.startswith("-") for a in args)  # no -m, --cfg, ...
            if plain and not show_traceback():
                cfg, problem = _compose_checked(config_name, args)
                if problem is not None:
                    report_user_error(problem, aliases)
                try:
                    startup_checks(cfg, check)
                except user_error_types() as err:
                    if not is_user_error(err):
                        raise
                    report_user_error(error_message(err), aliases)
            return hydra_main()

        return entry

    return decorate


def apply_extras(cfg: DictConfig, print_config: bool = True, validate: bool = True) -> None:
    """Validate the composed config (before any dump), then apply ``extras``.

    ``print_config=False`` leaves the dump (``extras.print_config``) to the caller's
    :func:`log_config`, for an entry point whose constructors check more before it
    (``sss2bathy-train`` instantiates its run first); ``validate=False`` leaves the check to
    :func:`sss2bathy.cli.train.fit`, which runs it next (once per run)."""
    from sss2bathy.config_validation import validate_config

    if validate:
        validate_config(cfg)
    extras = cfg.get("extras") or {}
    if extras.get("ignore_warnings"):
        warnings.filterwarnings("ignore", category=UserWarning)
        warnings.filterwarnings("ignore", category=FutureWarning)
    if print_config:
        log_config(cfg)


def _hydra_run_dir() -> Path | None:
    try:
        from hydra.core.hydra_config import HydraConfig

        return Path(HydraConfig.get().runtime.output_dir)
    except (ValueError, ImportError):
        return None


def log_config(cfg: DictConfig, run_dir: str | Path | None = None) -> Path | None:
    """With ``extras.print_config``: write the composed config to ``config.yaml`` in the run
    folder (``run_dir``, else the Hydra job's) and log where, the config itself at DEBUG
    only (a console or a redirected log keeps the run's own messages). Returns the file."""
    if not (cfg.get("extras") or {}).get("print_config"):
        return None
    text = OmegaConf.to_yaml(cfg, resolve=False)
    log.debug("composed config:\n%s", text)
    folder = Path(run_dir) if run_dir is not None else _hydra_run_dir()
    if folder is None:
        return None
    path = folder / "config.yaml"
    atomic_write_text(path, text)
    log.info("config: %s", path)
    return path


def git_revision() -> str | None:
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            cwd=project_root(),
            capture_output=True,
            text=True,
            check=True,
            timeout=10,
        )
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=project_root(),
            capture_output=True,
            text=True,
            timeout=10,
        ).stdout.strip()
        return out.stdout.strip() + ("-dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return None


def to_jsonable(metrics: Mapping[str, Any]) -> dict[str, float]:
    out = {}
    for k, v in metrics.items():
        try:
            out[k] = float(v)
        except (TypeError, ValueError):
            continue
    return out


def write_run_record(run_dir: Path, cfg: DictConfig, metrics: Mapping[str, Any]) -> None:
    """``run_info.json`` (task, experiment, git revision, seed) and ``metrics.json``."""
    run_dir.mkdir(parents=True, exist_ok=True)
    choices = {}
    try:
        from hydra.core.hydra_config import HydraConfig

        choices = dict(HydraConfig.get().runtime.choices)
    except ValueError:  # not under @hydra.main (compose API)
        pass
    info = {
        "task_name": cfg.get("task_name"),
        "experiment": choices.get("experiment"),
        "scale": choices.get("scale"),
        "survey": choices.get("data/survey"),
        "seed": cfg.get("seed"),
        "survey_name": OmegaConf.select(cfg, "data.survey.name"),
        "data_dir": OmegaConf.select(cfg, "paths.data_dir"),
        "git_revision": git_revision(),
    }
    atomic_write_text(run_dir / "run_info.json", json.dumps(info, indent=2))
    atomic_write_text(run_dir / "metrics.json", json.dumps(to_jsonable(metrics), indent=2))
