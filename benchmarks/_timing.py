"""What the benchmark scripts share: wall-clock timing of JAX calls, the machine's
description, and writing the results."""

import json
import pathlib
import platform
import time

import jax


def timed(function, *arguments) -> float:
    """Seconds for `function(*arguments)`, waiting for JAX's asynchronous dispatch."""
    start = time.perf_counter()
    jax.block_until_ready(function(*arguments))
    return time.perf_counter() - start


def machine() -> dict:
    return dict(processor=platform.processor(), cpus=jax.local_device_count(), backend=jax.default_backend())


def write(results: dict, path: str) -> None:
    out = pathlib.Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(dict(results, machine=machine(), jax=jax.__version__), indent=2))
    print(f"wrote {out}")
