"""The run's resolved config: what every process of one run must agree on.

A `RunConfig` is a `TrainConfig` with the `EnvSpec` of its environment, computed
once (`resolve`, through the environment's source, rendering nothing). It lives
in two places:

- the run folder's `config.json` (`open_folder`): the TrainConfig's fields at the
  top level, as `nasa train` writes them, plus `"spec"`. The first process to
  open the folder (`nasa up`, or the replay service under another launcher)
  writes it; every later one reads it and refuses to go on with other settings.
- the replay's `replay/config` queryable (`serve`): learner, actors and
  evaluator ask it at start (`join`), so a service started with other flags
  than its run refuses at once, naming the fields, instead of mixing two runs.

A refusal is `ConfigMismatch`, a bad-input error: a service exits with code 2
and `nasa up` does not restart it. Two kinds of field are not compared:
`LOCAL_FIELDS` (where a process runs, chosen by each) and, where the caller says
so, the step budget a resumed run may change (`may_change`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from shared import envs
from shared.config import ConfigError, TrainConfig, from_dict, to_dict, validate
from shared.files import replace_text

CONFIG_FILE = "config.json"
LOCAL_FIELDS: tuple[str, ...] = ("device",)
"""Fields each process chooses for itself: not compared between processes, not in the digest."""
RESUME_MAY_CHANGE: tuple[str, ...] = ("steps", "agent.cuda_graph")
"""What a resumed run may change: its step budget, and whether its updates are replayed as CUDA
graphs (the same arithmetic, run another way)."""


class ConfigMismatch(ConfigError):
    """A process started with other settings than its run's; names each differing field."""

    def __init__(self, where: str, fields: list[str], ours: TrainConfig, theirs: TrainConfig) -> None:
        self.fields = fields
        flags = " ".join(run_flags(fields, theirs))
        super().__init__(
            f"settings differ from the run's ({where}): {differences(fields, ours, theirs)}; "
            f"start it with the run's settings ({flags}), or start a new run in another folder"
        )


def differences(fields: list[str], ours: TrainConfig, theirs: TrainConfig) -> str:
    """Each of dotted config `fields` with its value in `ours` and in the run's `theirs`."""
    mine, run = flatten(ours), flatten(theirs)
    return ", ".join(f"{f} ({mine[f]!r} here, {run[f]!r} in the run)" for f in fields)


def run_flags(fields: list[str], run: TrainConfig) -> list[str]:
    """The flags that set dotted config `fields` to the run's values, one string each."""
    values = flatten(run)
    return [_flag_of(f, values[f]) for f in fields]


def _flag_of(field: str, value: object) -> str:
    """The command-line flag that sets dotted config field `field` to `value`: a run's settings
    come from flags named after the field alone (`agent.latent_dim`: `--latent-dim`), a bool's
    as --name / --no-name. A default that changed since a run began (SAC-AE's warm-up burst) is
    refused at its relaunch, and this names what restores the run's."""
    name = field.rsplit(".", 1)[-1].replace("_", "-")
    if isinstance(value, bool):
        return f"--{name}" if value else f"--no-{name}"
    return f"--{name} {value}"


@dataclass(frozen=True)
class RunConfig:
    config: TrainConfig
    spec: envs.EnvSpec

    def digest(self) -> str:
        """sha256 (16 hex chars) of the canonical JSON of what the run's processes share
        (the config without LOCAL_FIELDS, and the spec): equal digests, same run settings."""
        shared = {k: v for k, v in self.to_dict().items() if k not in LOCAL_FIELDS}
        canonical = json.dumps(shared, sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(canonical.encode()).hexdigest()[:16]

    def to_dict(self) -> dict:
        """The TrainConfig's fields at the top level (as `nasa train`'s config.json) plus "spec"."""
        return {**to_dict(self.config), "spec": self.spec.to_dict()}

    @classmethod
    def from_dict(cls, d: dict) -> RunConfig:
        d = dict(d)
        if "spec" not in d:
            raise ConfigError("the run's config has no environment spec")
        spec = envs.EnvSpec.from_dict(d.pop("spec"))
        return cls(config_from_dict(d), spec)


def config_from_dict(d: dict) -> TrainConfig:
    """A TrainConfig from a dict, as a ConfigError naming what is wrong (not a TypeError)."""
    try:
        return from_dict(d)
    except (TypeError, ValueError) as err:
        raise ConfigError(f"not a config this version reads: {err}") from err


def flatten(config: TrainConfig) -> dict[str, object]:
    """Dotted field name -> value, e.g. {"agent.latent_dim": 200, ...}."""
    out: dict[str, object] = {}

    def walk(prefix: str, obj: object) -> None:
        for f in dataclasses.fields(obj):  # type: ignore[arg-type]
            value = getattr(obj, f.name)
            if dataclasses.is_dataclass(value):
                walk(f"{prefix}{f.name}.", value)
            else:
                out[prefix + f.name] = value

    walk("", config)
    return out


def differing_fields(a: TrainConfig, b: TrainConfig, ignore: tuple[str, ...] = ()) -> list[str]:
    """Dotted names of the fields whose values differ (e.g. "agent.latent_dim"), in declaration order."""
    fa, fb = flatten(a), flatten(b)
    return [name for name in fa if name not in ignore and fa[name] != fb[name]]


def check_same(config: TrainConfig, run: TrainConfig, where: str, may_change: tuple[str, ...] = ()) -> None:
    """Raise ConfigMismatch unless `config` has the run's settings (LOCAL_FIELDS and `may_change` aside)."""
    fields = differing_fields(config, run, ignore=LOCAL_FIELDS + tuple(may_change))
    if fields:
        raise ConfigMismatch(where, fields, config, run)


def resolve(config: TrainConfig) -> RunConfig:
    """The config validated, with its environment's spec (the one probe of the environment)."""
    validate(config)
    return RunConfig(config, envs.spec(config.env))


def read_config(path: Path) -> TrainConfig:
    """The TrainConfig of a config.json file (a RunConfig's, or one `nasa train` wrote without a spec)."""
    body = read_json_object(Path(path))
    body.pop("spec", None)
    return config_from_dict(body)


def read_folder(data: Path) -> dict | None:
    """The run folder's config.json as a dict, or None when there is none."""
    path = Path(data) / CONFIG_FILE
    return read_json_object(path) if path.exists() else None


def read_json_object(path: Path, error: type[Exception] = ConfigError, what: str = "a config") -> dict:
    """The JSON object in `path`; a file that cannot be read or parsed, or holds something else,
    raises `error` naming it."""
    try:
        body = json.loads(Path(path).read_bytes())
    except (OSError, ValueError) as err:
        raise error(f"{path} is unreadable: {err}") from err
    if not isinstance(body, dict):
        raise error(f"{path} is unreadable: it does not hold {what}")
    return body


def write_folder(data: Path, run: RunConfig) -> None:
    """Write <data>/config.json atomically (a reader never sees half a file)."""
    data = Path(data)
    data.mkdir(parents=True, exist_ok=True)
    replace_text(data / CONFIG_FILE, json.dumps(run.to_dict(), indent=2) + "\n",
                 tmp=data / f".{CONFIG_FILE}.{os.getpid()}.tmp")


def open_folder(config: TrainConfig, data: Path, may_change: tuple[str, ...] = ()) -> RunConfig:
    """The run's RunConfig for the run folder `data`.

    A new folder: resolve `config` and write <data>/config.json. A folder that has
    one: compare (ConfigMismatch naming the differing fields). The fields that may
    differ (LOCAL_FIELDS, and `may_change`: a resumed run's new step budget) are
    taken from `config` and the file rewritten, so the services a launcher starts
    with --run-config get them. A config.json without a spec (written by an older
    version) gets one.
    """
    body = read_folder(data)
    if body is None:
        run = resolve(config)
        write_folder(data, run)
        return run
    saved = body.pop("spec", None)
    theirs = config_from_dict(body)
    check_same(config, theirs, f"{Path(data) / CONFIG_FILE}", may_change)
    if saved is None:
        run = resolve(config)
    else:
        run = RunConfig(validate(config), envs.EnvSpec.from_dict(saved))
    if saved is None or differing_fields(config, theirs):
        write_folder(data, run)
    return run


def message(run: RunConfig):  # noqa: ANN201 (a wire.RunConfigMsg)
    from shared import wire

    return wire.RunConfigMsg(run_config=run.to_dict(), digest=run.digest())


def join(config: TrainConfig, session, keys, stop, timeout_s: float = 5.0,  # noqa: ANN001
         retry_s: float = 0.5) -> RunConfig | None:
    """Ask the replay's `keys.config` queryable for the run's RunConfig, until it answers or `stop`
    is set (then None); ConfigMismatch if `config` differs from it (LOCAL_FIELDS aside).

    Returns the caller's `config` (its LOCAL_FIELDS are its own) with the run's spec.
    `stop` is anything with `wait(seconds) -> bool` (a StopFlag, a threading.Event).
    """
    from shared import wire

    while not stop.wait(0):
        for reply in session.get(keys.config, timeout=timeout_s):
            if reply.ok is None:
                continue
            try:
                msg = wire.decode(reply.ok.payload.to_bytes(), wire.RunConfigMsg)
            except wire.WireError as err:  # another version's replay: restarting would not help
                raise ConfigError(f"run {keys.run_id}: the replay's config is unreadable: {err}") from err
            run = RunConfig.from_dict(msg.run_config)
            check_same(config, run.config, f"run {keys.run_id}, as its replay holds it")
            return RunConfig(config, run.spec)
        stop.wait(retry_s)
    return None


@contextlib.contextmanager
def serve(session, keys, run: RunConfig) -> Iterator[None]:  # noqa: ANN001
    """The replay's side of `join`: answer queries on `keys.config` with `run` while open."""
    from shared import wire

    payload = wire.encode(message(run))

    def on_query(query) -> None:  # noqa: ANN001
        query.reply(keys.config, payload)

    queryable = session.declare_queryable(keys.config, on_query)
    try:
        yield
    finally:
        queryable.undeclare()
