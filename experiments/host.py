"""The host a benchmark ran on, for its table: the CPU model and core count."""

from __future__ import annotations

import os
import platform
from pathlib import Path


def cpu_name() -> str:
    """The CPU model (``/proc/cpuinfo``'s first ``model name``), else what ``platform`` says."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def describe() -> str:
    """``"<CPU model> (<n> cores)"``."""
    return f"{cpu_name()} ({os.cpu_count()} cores)"


def fresh_process_json(script: str, args: list[str], xla_flags: str | None) -> dict | None:
    """The last stdout line, read as JSON, of ``python script *args`` in a fresh process with
    ``XLA_FLAGS`` set to ``xla_flags`` (unset for None): the CPU switches are process-wide, so
    a benchmark times the path without them in a process of its own. None (with a line on
    stdout) when the process fails."""
    import json
    import subprocess
    import sys

    env = dict(os.environ)
    env.pop("XLA_FLAGS", None)
    if xla_flags:
        env["XLA_FLAGS"] = xla_flags
    cmd = [sys.executable, script, *args]
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, check=True, timeout=1800, env=env)
    except (subprocess.SubprocessError, OSError) as err:
        print(f"fresh-process comparison failed: {err}", flush=True)
        return None
    return json.loads(out.stdout.strip().splitlines()[-1])


def add_cpu_switch_args(parser) -> None:
    """``--no-tune-malloc`` and ``--no-tune-xla`` (both on by default) on a benchmark's parser."""
    parser.add_argument("--tune-malloc", dest="tune_malloc", action="store_true", default=True)
    parser.add_argument("--no-tune-malloc", dest="tune_malloc", action="store_false")
    parser.add_argument(
        "--tune-xla",
        dest="tune_xla",
        action="store_true",
        default=True,
        help="add cpu_tuning.xla_cpu_flags(library_fusions=False) to XLA_FLAGS (default)",
    )
    parser.add_argument("--no-tune-xla", dest="tune_xla", action="store_false")


def cpu_switches(tune_malloc: bool, tune_xla: bool) -> tuple[bool, str]:
    """Turn on a benchmark's CPU switches before JAX allocates or reads its flags:
    ``cpu_tuning.tune_malloc()`` and ``cpu_tuning.xla_cpu_flags(library_fusions=False)``
    added to ``XLA_FLAGS``. Returns ``(malloc tuned, XLA_FLAGS as the environment gave
    them)``, the latter for a fresh process without the flags."""
    from cpf_jax.cpu_tuning import tune_malloc as _tune_malloc
    from cpf_jax.cpu_tuning import xla_cpu_flags

    given = os.environ.get("XLA_FLAGS", "")
    tuned = _tune_malloc() if tune_malloc else False
    flag = xla_cpu_flags(library_fusions=False)
    if tune_xla and flag not in given.split():
        os.environ["XLA_FLAGS"] = f"{given} {flag}".strip()
    return tuned, given
