"""The Hydra plumbing shared by the ``uabs-train`` and ``uabs-traces`` entry points."""

from __future__ import annotations

import dataclasses
import difflib
import itertools
import logging
import math
import os
import re
import shutil
import signal
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml
from omegaconf import OmegaConf, open_dict

from uabs_rl.cli import parallel
from uabs_rl.config import (
    CONF_DIR,
    ConfigError,
    check_config_dirs,
    check_duplicate_overrides,
    check_group_choices,
    check_moved_overrides,
    chooses_study,
    command_line_overrides,
    flatten,
    override_key,
    register_configs,
    to_container,
)
from uabs_rl.paths import safe_component
from uabs_rl.runs.checkpoint import CheckpointError, Interrupted
from uabs_rl.runs.folder import Before
from uabs_rl.runs.layout import HYDRA, IDENTITY, LOCK, STOP_ENV

# the launchers that submit to SLURM (conf/hydra/launcher/slurm.yaml, and submitit's own)
SLURM_LAUNCHERS = ("slurm", "submitit_slurm")


def _submits_to_slurm(value: str, dirs: list[Path]) -> bool:
    """Whether the launcher option ``value`` submits to SLURM: the package's
    (``slurm``) or submitit's, or a file of a --config-dir's ``hydra/launcher/`` that
    builds on submitit's."""
    if value in SLURM_LAUNCHERS:
        return True
    for d in dirs:
        path = Path(d) / "hydra" / "launcher" / f"{value}.yaml"
        if path.is_file():
            try:
                data = yaml.safe_load(path.read_text()) or {}
            except (OSError, yaml.YAMLError):
                return False
            defaults = data.get("defaults", []) if isinstance(data, dict) else []
            return any("submitit_slurm" in str(x) for x in defaults)
    return False


def start_folders(argv: list[str]) -> list[Path]:
    """The folders a command line may write a run in or under: those it names
    (``hydra.run.dir``, ``hydra.sweep.dir``, ``resume``) and the default run and sweep
    folders (``outputs/runs``, ``outputs/multirun``)."""
    out = [Path("outputs/runs"), Path("outputs/multirun")]
    for a in argv:
        key, _, value = a.partition("=")
        if key in ("hydra.run.dir", "hydra.sweep.dir", "resume") and value.strip("'\""):
            out.append(Path(value.strip("'\"").replace("\\'", "'")))
    return out


# Hydra settings the project owns: where a run's record and log go (a run writes its
# own .hydra/ record once its checks pass, and its log is <job name>.log in its folder)
OWNED = ("hydra.output_subdir", "hydra.job.name", "hydra.job.chdir", "hydra.job_logging",
         "hydra/job_logging", "hydra.hydra_logging", "hydra/hydra_logging", "hydra.runtime")


def config_groups() -> set[str]:
    """The config groups of the package's ``conf/`` (``scenario``, ``masking``, ...)."""
    return {d.name for d in CONF_DIR.iterdir() if d.is_dir()}


def check_command_line(argv: list[str]) -> None:
    """Refuse, before Hydra reads them, overrides Hydra would fail on in several lines
    (its grammar), a Hydra setting the project owns (``OWNED``), a config group option
    that is a path (``scenario=../elsewhere/x`` would load any YAML file: an option is
    a file name of the group's folder, or of ``--config-dir``'s), and a setting given
    twice through a mapping (``train={episodes: 2} train.episodes=1``)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    words = command_line_overrides(argv)
    try:
        OverridesParser.create().parse_overrides(overrides=words)
    except HydraException as e:
        first = (str(e).strip().splitlines() or [type(e).__name__])[0]
        raise ConfigError(f"the command line does not parse: {first} (quote a value "
                          f"holding brackets, braces, commas, spaces or an =, for the shell "
                          f"too: \"key='a=b'\").") from None
    groups = config_groups()
    keys = []
    for word in words:
        key = override_key(word)
        if key is None:
            continue
        keys.append(key)
        if key.startswith(OWNED) or key in OWNED:
            raise ConfigError(f"{key} is set by uabs_rl itself (a run writes its own "
                              f"record and log into its folder): leave it out.")
        if key in groups:
            for option in word.partition("=")[2].split(","):
                option = option.strip().strip("'\"")
                safe_component(option, key)
                if option.endswith("_schema") and not (CONF_DIR / key / f"{option}.yaml"
                                                       ).is_file():  # a typed base (store.py)
                    choices = sorted(p.stem for p in (CONF_DIR / key).glob("*.yaml"))
                    raise ConfigError(f"{key}={option} is the schema the options of {key} "
                                      f"build on, not one of them: choose from "
                                      f"{', '.join(choices)}.")
    for key in keys:
        wider = next((k for k in keys if key.startswith(k + ".") and k not in groups), None)
        if wider is not None:
            raise ConfigError(f"{key} is given twice on the command line (once inside "
                              f"{wider}={{...}}): give it once.")


# Hydra's command-line flags after which a composition here would not be Hydra's (another
# config folder, a printout instead of a run): the pre-check leaves those to Hydra
_OWN_FLAGS = ("--config-path", "-cp", "--config-name", "-cn",
              "--cfg", "-c", "--help", "-h", "--hydra-help", "--info", "-i", "--resolve",
              "--package", "-p", "--shell-completion", "-sc", "--experimental-rerun")
_CONFIG_DIR = ("--config-dir", "-cd")


def quoted(value: str) -> str:
    """``value`` as a quoted string of Hydra's override grammar (a path may hold = , [ ')."""
    return "'" + value.replace("\\", "\\\\").replace("'", "\\'") + "'"


def search_overrides(dirs: list[Path]) -> list[str]:
    """The override that adds ``--config-dir``'s folders to a composition's search path
    (none without them)."""
    return ([f"hydra.searchpath=[{','.join(quoted(f'file://{d.resolve()}') for d in dirs)}]"]
            if dirs else [])


def config_dirs(argv: list[str]) -> list[Path]:
    """The folders of ``--config-dir D`` (``-cd D``, ``--config-dir=D``) on a command
    line."""
    out = []
    for i, a in enumerate(argv):
        flag, eq, value = a.partition("=")
        if flag in _CONFIG_DIR:
            value = value if eq else (argv[i + 1] if i + 1 < len(argv) else "")
            out.append(Path(value))
    return out


# the command of each config (its messages name it)
COMMANDS = {"config": "uabs-train", "build_traces": "uabs-traces"}

# a sweep of at most this many jobs has each job's settings checked before any starts
# (each a composition, ~0.1 s); of a longer sweep, each setting's first values
MOST_JOBS_CHECKED = 32


def check_composition(config_name: str, argv: list[str],
                      check: Callable[[Any], None] | None = None) -> None:
    """Compose the command line's config as Hydra is about to (each value of a sweep in
    turn): a misspelt key, a group option that does not exist or a value of the wrong
    type is a :class:`ConfigError` of one line naming it and what to type instead, where
    Hydra prints its message over 7 to 13 lines and exits with status 1. Only Hydra's
    composition is tried here, and with ``check`` (the run's own start-up checks, on the
    composed config) each job of a sweep of at most :data:`MOST_JOBS_CHECKED`, so a value
    one job would refuse stops the sweep before any job runs."""
    from hydra import compose, initialize_config_dir
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    words = command_line_overrides(argv)
    if any(a.split("=", 1)[0] in _OWN_FLAGS for a in argv) or any(
            w.lstrip("+~").startswith("hydra.searchpath") for w in words):
        return  # another primary config or search path: Hydra's composition alone
    dirs = config_dirs(argv)
    groups = config_groups()
    typed = next((a.partition("=")[0] for a in argv if a.partition("=")[0] in _CONFIG_DIR),
                 "--config-dir")  # its messages name the flag as typed (-cd or --config-dir)
    check_config_dirs(dirs, [(w.split("=", 1)[0], v.strip().strip("'\""))
                             for w in words if w.split("=", 1)[0] in groups
                             for v in w.split("=", 1)[1].split(",")], flag=typed)
    # where Hydra looks beside conf/: the same folders, for this composition
    search = search_overrides(dirs)
    register_configs()  # the groups' typed bases (idempotent)
    multirun = any(a in ("-m", "--multirun") for a in argv) or "hydra.mode=MULTIRUN" in words
    for w in words:
        key, _, value = w.partition("=")
        if key == "hydra.launcher.n_jobs" and value.strip("'\"") in ("0", "-0"):
            raise ConfigError(f"hydra.launcher.n_jobs={value}: the jobs a sweep runs at "
                              f"once must be a whole number >= 1 (or -1: one per core).")
        launcher = value.strip("'\"") if key == "hydra/launcher" else ""
        if launcher and _submits_to_slurm(launcher, dirs):
            if not multirun:  # Hydra would train here, one run, without a word
                raise ConfigError(
                    f"hydra/launcher={launcher} submits a sweep's jobs to SLURM, but without -m "
                    f"this command trains here, one run: add -m (uabs-train -m ...) to "
                    f"submit, or leave the launcher out.")
            if shutil.which("srun") is None:  # submitit's traceback, after a folder
                raise ConfigError(
                    f"hydra/launcher={launcher} submits each job to SLURM, but this machine has "
                    f"no srun on its PATH (not a SLURM node): start the sweep on your "
                    f"cluster's login node, or run it here with hydra/launcher=local_parallel.")
    try:
        parsed = OverridesParser.create().parse_overrides(overrides=words)
        sweeps = [o.input_line for o in parsed if o.is_sweep_override()
                  and not o.get_key_element().lstrip("+~").startswith("hydra")]
        if sweeps and not multirun:
            raise ConfigError(f"{sweeps[0]} is a sweep (several values): add -m to run one "
                              f"job per value ({COMMANDS.get(config_name, 'uabs-train')} "
                              f"-m ...), or give one value.")
        fixed = [o.input_line for o in parsed if not o.is_sweep_override()]
        listed = [[f"{o.get_key_element()}={v}" for v in o.sweep_string_iterator()]
                  for o in parsed if o.is_sweep_override() and not o.is_interval_sweep()]
        # every job of the sweep, composed and checked, where they are few enough (an
        # interval sweep's values, a study's trials, are drawn, not listed: a study stops
        # on refusals itself); else the fixed settings, then each listed value with them
        # (a composition is ~0.1 s: a long sweep's first values only)
        jobs = (check is not None and 1 < math.prod(map(len, listed)) <= MOST_JOBS_CHECKED
                and not any(o.is_interval_sweep() for o in parsed)
                and not chooses_study(words))
        tries = ([fixed + list(job) for job in itertools.product(*listed)] if jobs else
                 [fixed, *(fixed + [v] for values in listed
                           for v in values[:MOST_JOBS_CHECKED])])
    except HydraException:  # a sweep this cannot list: Hydra's own path decides
        return
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        for overrides in tries:
            mine = [o for o in overrides if not o.lstrip("+~").startswith("hydra")]
            try:
                composed = compose(config_name=config_name, overrides=search + mine,
                                   return_hydra_config=True)
            except (yaml.YAMLError, UnicodeDecodeError) as e:  # a file of --config-dir's
                # that is not YAML (or not text)
                where = getattr(e, "problem_mark", None)
                raise ConfigError(f"{where.name if where else 'a config file'} is not a "
                                  f"readable YAML file ({getattr(e, 'problem', None) or e}"
                                  f"{f', line {where.line + 1}' if where else ''}): fix it "
                                  f"or choose another option.") from None
            except HydraException as e:
                cause = f"\n{e.__cause__}" if e.__cause__ is not None else ""
                known = []  # the settings there are, with the groups and presets
                for chosen in ([o for o in mine if "." not in o.split("=", 1)[0]], []):
                    try:  # chosen (else the defaults': an option's file may be at fault)
                        known = list(flatten(OmegaConf.to_container(compose(
                            config_name=config_name, overrides=search + chosen),
                            resolve=False)))
                        break
                    except HydraException:
                        continue
                raise ConfigError(composition_error(
                    f"{e}{cause}", known, bool(dirs),
                    COMMANDS.get(config_name, "uabs-train"))) from None
            except Exception:  # anything else (scenario=null, ...): Hydra's own answer
                return
            choices = composed.hydra.runtime.choices
            with open_dict(composed):
                del composed["hydra"]
            try:
                from uabs_rl.training.startup import registered_names  # torch: here

                check_group_choices(choices, composed, [CONF_DIR, *dirs], mine,
                                    registered_names())
            except ConfigError as e:  # a sweep's value names its job; a fixed one not
                swept = [j for j in mine if j not in fixed
                         and j.partition("=")[0].lstrip("+") == getattr(e, "key", None)]
                raise ConfigError(f"the job {swept[0]} of this sweep: {e} No job was "
                                  f"started." if swept else str(e)) from None
            if not jobs:  # one run checks itself as it starts
                continue
            try:
                check(composed)
            except ConfigError as e:
                which = " ".join(j for j in mine if j not in fixed)
                raise ConfigError(f"the job {which} of this sweep: {e} No job was "
                                  f"started.") from None
            except Exception:  # anything else is the job's to report, as it starts
                return


def composition_error(message: str, known: list[str] = (), yours: bool = False,
                      command: str = "uabs-train") -> str:
    """Hydra's message of a failed composition as one line: what is wrong and what to
    type instead (the options of a group without its schema, ``<group>_schema``; for a
    key no setting has, the closest of ``known``, the config's settings)."""
    lines = [ln.strip() for ln in message.strip().splitlines() if ln.strip()]
    text = " ".join(lines)
    missing = re.search(r"Could not find '([^']+)/([^']+)'", text)
    if missing:
        group, option = missing.groups()
        options = [ln for ln in lines[lines.index(next(
            ln for ln in lines if ln.startswith("Available options"))) + 1:]
            if not ln.startswith(("Config search path", "provider="))] if any(
            ln.startswith("Available options") for ln in lines) else []
        options = [o for o in options if not o.endswith("_schema")]
        where = f"conf/{group}/" + (f" and your --config-dir's {group}/" if yours else "")
        return (f"{group}={option}: {group} has no option {option!r}; choose from "
                f"{', '.join(options)} (the files of {where}; an option of yours is its "
                f"file, {group}/{option}.yaml: docs/code.md, Extending).")
    in_file = re.search(r"In '([^']+)': ConfigKeyError.*Key '([^']+)' not in '([^']+)'",
                        text)
    if in_file:  # a key in an option's file that its section does not have
        option, missing, schema = in_file.groups()
        from uabs_rl.config import schema as schemas  # the keys of the class named

        cls = getattr(schemas, schema, None)
        keys = [f.name for f in dataclasses.fields(cls)] if dataclasses.is_dataclass(
            cls) else []
        close = difflib.get_close_matches(missing, keys, n=3, cutoff=0.6)
        hint = f"did you mean {' or '.join(close)}? " if close else ""
        return (f"{option}.yaml sets {missing!r}, which {schema} does not have: {hint}fix "
                f"the file ({command} --cfg job prints every setting).")
    unknown = re.search(r"Could not override '([^']+)'.*Key '([^']+)' not in '([^']+)'", text)
    if unknown:
        key, missing, schema = unknown.groups()
        close = difflib.get_close_matches(key, sorted(known), n=3, cutoff=0.6)
        hint = f"did you mean {' or '.join(close)}? " if close else ""
        return (f"{key} is not a setting ({schema} has no {missing!r}): "
                f"{hint}fix its spelling; {command} --cfg job prints every setting.")
    first = next((i for i, ln in enumerate(lines) if ln.startswith("Error merging override ")),
                 None)
    if first is not None:
        override = lines[first][len("Error merging override "):]
        detail = next((ln for ln in lines[first + 1:] if not ln.startswith(
            ("full_key:", "reference_type=", "object_type=", "Set the environment"))), "")
        return f"{override}: {detail.rstrip('.')}."
    return " ".join(ln for ln in lines if not ln.startswith(
        ("full_key:", "reference_type=", "object_type=", "Set the environment variable")))


def path_safe(text: str) -> str:
    """``text`` (a run's overrides) as one folder name: a ``/`` in a value (a file path,
    ``..``) would nest the run folder or lead it out of ``outputs/``; it reads ``%2F``."""
    return str(text).replace("/", "%2F")


def hydra_main(config_name: str, body: Callable[..., Any],
               pass_overrides: bool = False,
               check: Callable[[Any], None] | None = None) -> None:
    """Run ``body(cfg, output_dir[, overrides])`` under ``@hydra.main`` (a sweep's job
    returns what ``body`` returns) with
    ``conf/<config_name>``: the config arrives as checked dataclasses; a config or
    checkpoint error is one line on stderr and exit status 2, Ctrl-C one line and
    status 130 (143 after SIGTERM), never a traceback."""
    interrupted = ("interrupted: the last checkpoint, if the run had one, is kept"
                   if pass_overrides else "interrupted")
    import hydra
    from hydra.core.hydra_config import HydraConfig

    def app(dcfg) -> Any:
        hc = HydraConfig.get()
        # a log file that cannot be written (a full disk) loses lines, not the run
        # (the run says what failed, in one line); no "--- Logging error ---" traces
        logging.raiseExceptions = False
        extra = (list(hc.overrides.task),) if pass_overrides else ()
        out = Path(hc.runtime.output_dir)
        ours = {HYDRA, LOCK, IDENTITY, f"{hc.job.name}.log"}
        stop = parallel.job_stop_file(hc)  # a job of a parallel sweep: None otherwise
        if stop is not None:
            parallel.job_signals(running=True)
            os.environ[STOP_ENV] = str(stop)  # training stops when the sweep does
        try:
            if stop is not None and stop.exists():  # the sweep stopped before this job
                before.undo_start(out, ours)
                return None
            # a group option whose file does not name itself (where the pre-check
            # above did not compose: another search path)
            from uabs_rl.training.startup import registered_names

            check_group_choices(hc.runtime.choices, dcfg,
                                [Path(c.path) for c in hc.runtime.config_sources
                                 if c.schema == "file"], hc.overrides.task,
                                registered_names())
            return body(to_container(dcfg), out, *extra)
        except (ConfigError, CheckpointError, OSError) as e:
            # only what this invocation made: never a folder or file that was there
            before.undo_start(out, ours)
            if isinstance(e, OSError):  # a path the file system refuses (too long, ...)
                where = f" ({e.filename})" if getattr(e, "filename", None) else ""
                e = f"{e.strerror or e}{where}: check the paths of the command line and " \
                    f"their file system."
            print(f"error: {e}", file=sys.stderr)
            sys.exit(2)
        except Interrupted as e:
            print(str(e), file=sys.stderr)
            from uabs_rl.training.experiment import Stopped

            if stop is not None and isinstance(e, Stopped):  # saved: the sweep goes on
                # to its end (no other job starts), where its launcher says it stopped
                parallel.stop_sweep(stop, e.exit_code - 128)
                return None
            sys.exit(getattr(e, "exit_code", 130))
        except KeyboardInterrupt as e:  # a second Ctrl-C, or one outside training
            from uabs_rl.training.experiment import StoppedNow

            if stop is not None and not isinstance(e, StoppedNow):
                # a parallel sweep's job stopped before or after its training: nothing
                # to save (a run folder it began is kept: undo_start removes only a
                # folder that holds nothing but the start's own records)
                before.undo_start(out, ours)
                parallel.stop_sweep(stop, e.signum if isinstance(e, parallel.JobSignal)
                                    else signal.SIGINT)
                return None
            print(str(e) or interrupted, file=sys.stderr)
            sys.exit(getattr(e, "exit_code", 130))
        finally:
            if stop is not None:
                parallel.job_signals(running=False)
                os.environ.pop(STOP_ENV, None)
                parallel.exit_if_orphaned()

    try:  # before Hydra, whose own message would not say what to type instead
        check_moved_overrides(sys.argv[1:])
        check_duplicate_overrides(sys.argv[1:])
        check_command_line(sys.argv[1:])
        check_composition(config_name, sys.argv[1:], check)
    except ConfigError as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
    before = Before(start_folders(sys.argv[1:]))  # what exists before Hydra makes folders
    register_configs()
    # ${prefixed:_,<text>}: "_<text>", or nothing when <text> is empty (run folder names)
    OmegaConf.register_new_resolver("prefixed", lambda sep, text: f"{sep}{text}" if text
                                    else "", replace=True)
    # ${path_safe:<text>}: <text> as one folder name (run and sweep job folder names)
    OmegaConf.register_new_resolver("path_safe", path_safe, replace=True)
    try:
        hydra.main(version_base="1.3", config_path=str(CONF_DIR),
                   config_name=config_name)(app)()
    except parallel.SweepStopped as e:  # raised by the parallel launcher, after its jobs
        print(str(e), file=sys.stderr)
        sys.exit(e.exit_code)
