"""Bounded YAML loading for every YAML file the suite reads (configs, inventories, experiments,
calibrations, rigs, paths, run.yaml).

PyYAML's ``safe_load`` refuses arbitrary objects but not arbitrary *size*: a few hundred bytes of
nested anchors and aliases (a "billion laughs") expand to gigabytes, and deep nesting ends in a
RecursionError. Here a document is checked as a stream of parser events first, which costs
constant memory, and refused before anything is built when it

- is larger than ``MAX_BYTES`` on disk, or is not UTF-8,
- uses an anchor (``&a``) or an alias (``*a``): none of our files need them, and without them
  the document's size bounds its expansion,
- nests deeper than ``MAX_DEPTH`` collections, or
- holds more than ``MAX_NODES`` nodes (a node costs about 400 bytes once built).

Only then is it loaded, with libyaml when it is installed. Every problem is one
:class:`YamlError` line that names the file (and the line, where there is one). Callers turn it
into their own error type. :func:`dump` writes YAML that never contains anchors, so files this
suite writes are files it can read back.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any, overload

import yaml

MAX_BYTES = 8 * 1024 * 1024
MAX_DEPTH = 64
MAX_NODES = 250_000

# libyaml's parser and composer when present (about 6x faster than the pure-Python ones). The
# stubs declare the C classes apart from the Python ones, with the same methods: the checker is
# shown the Python classes.
if TYPE_CHECKING:
    BaseLoader = yaml.SafeLoader
    _BaseDumper = yaml.SafeDumper
else:
    BaseLoader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
    _BaseDumper = getattr(yaml, "CSafeDumper", yaml.SafeDumper)


class YamlError(ValueError):
    """A YAML file that cannot be read, is not valid YAML, or exceeds the limits; one line that
    names the file."""


class SafeLoader(BaseLoader):
    """The safe loader used here; subclass it to add constructors (e.g. OpenCV's matrix tag)."""


class _NoAliasDumper(_BaseDumper):
    def ignore_aliases(self, data: Any) -> bool:
        return True


def _where(source: str, mark: Any) -> str:
    return f"{source}:{mark.line + 1}" if mark is not None else source


def _yaml_problem(e: yaml.YAMLError) -> tuple[Any, str]:
    mark = getattr(e, "problem_mark", None) or getattr(e, "context_mark", None)
    problem = getattr(e, "problem", None) or getattr(e, "context", None)
    if not problem:
        problem = (str(e).strip().splitlines() or [type(e).__name__])[0]
    return mark, " ".join(str(problem).split())


def _check_events(text: str, source: str, loader: type, max_depth: int, max_nodes: int) -> None:
    """Walk the parser's events (constant memory) and refuse aliases, depth and node count."""
    parser = loader(text)
    depth = nodes = 0
    try:
        while parser.check_event():
            ev = parser.get_event()
            if isinstance(ev, yaml.AliasEvent):
                raise YamlError(
                    f"{_where(source, ev.start_mark)}: aliases (*{ev.anchor}) are not "
                    "allowed; write the value out"
                )
            if isinstance(ev, yaml.NodeEvent):
                if ev.anchor is not None:
                    raise YamlError(
                        f"{_where(source, ev.start_mark)}: anchors (&{ev.anchor}) are "
                        "not allowed; write the value out"
                    )
                nodes += 1
                if nodes > max_nodes:
                    raise YamlError(
                        f"{_where(source, ev.start_mark)}: more than {max_nodes} values "
                        "in one document"
                    )
                if isinstance(ev, yaml.CollectionStartEvent):
                    depth += 1
                    if depth > max_depth:
                        raise YamlError(
                            f"{_where(source, ev.start_mark)}: nested deeper than "
                            f"{max_depth} levels"
                        )
            elif isinstance(ev, yaml.CollectionEndEvent):
                depth -= 1
    except yaml.YAMLError as e:
        mark, problem = _yaml_problem(e)
        if "nesting depth" in problem:  # libyaml in PyYAML >= 6.0.4 stops runaway nesting itself
            raise YamlError(
                f"{_where(source, mark)}: nested deeper than {max_depth} levels"
            ) from None
        raise YamlError(f"{_where(source, mark)}: not valid YAML ({problem})") from None
    finally:
        parser.dispose()


def loads(
    text: str | bytes,
    source: str = "<yaml>",
    *,
    loader: type | None = None,
    max_depth: int = MAX_DEPTH,
    max_nodes: int = MAX_NODES,
) -> Any:
    """Parse one YAML document (``None`` when it is empty) within the limits; YamlError else.

    ``loader`` must be :class:`SafeLoader` or a subclass of it."""
    loader = loader or SafeLoader
    if not issubclass(loader, SafeLoader):
        raise TypeError("loader must be safe_yaml.SafeLoader or a subclass of it")
    if isinstance(text, bytes):
        text = decode_utf8(text, source)
    if text.startswith("\ufeff"):
        text = text[1:]
    _check_events(text, source, loader, max_depth, max_nodes)
    try:
        return yaml.load(text, Loader=loader)  # noqa: S506 - a SafeLoader subclass
    except yaml.YAMLError as e:
        mark, problem = _yaml_problem(e)
        raise YamlError(f"{_where(source, mark)}: not valid YAML ({problem})") from None
    except (ValueError, TypeError, OverflowError) as e:
        # a constructor choking on a value: an int of 5,000 digits, a date like 2024-13-45
        problem = " ".join(str(e).split()) or type(e).__name__
        raise YamlError(f"{source}: a value cannot be read ({problem})") from None


def decode_utf8(data: bytes, source: str) -> str:
    """Bytes -> text, or YamlError naming the line and byte offset of the first bad byte."""
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as e:
        line = data.count(b"\n", 0, e.start) + 1
        raise YamlError(
            f"{source}:{line}: not UTF-8 text (byte {data[e.start]:#04x} at offset {e.start})"
        ) from None


def read_bytes_limited(path: str | Path, max_bytes: int = MAX_BYTES) -> bytes:
    """The file's bytes, or YamlError if it cannot be read or is larger than ``max_bytes``
    (checked on what is read, so a growing file or a device cannot slip past)."""
    from bgt_core.safe_open import FileRefused, open_regular

    path = Path(path)
    try:
        # Only a regular file; its size is checked below, in this module's own words.
        with open_regular(path, "yaml", max_bytes=sys.maxsize) as f:
            size = os.fstat(f.fileno()).st_size
            if size > max_bytes:
                raise YamlError(f"{path}: {size} bytes; a YAML file may be at most {max_bytes}")
            data = f.read(max_bytes + 1)
    except FileRefused as e:
        raise YamlError(str(e)) from None
    except OSError as e:
        raise YamlError(f"{path}: cannot read ({e.strerror or e})") from None
    if len(data) > max_bytes:
        raise YamlError(f"{path}: larger than {max_bytes} bytes, the most a YAML file may be")
    return data


def load_file(
    path: str | Path,
    *,
    loader: type | None = None,
    max_bytes: int = MAX_BYTES,
    max_depth: int = MAX_DEPTH,
    max_nodes: int = MAX_NODES,
    preprocess: Any = None,
) -> Any:
    """Read and parse a YAML file within the limits; every problem is one YamlError line.

    ``preprocess`` (text -> text) runs on the decoded text before parsing."""
    source = str(path)
    text = decode_utf8(read_bytes_limited(path, max_bytes), source)
    if preprocess is not None:
        text = preprocess(text)
    return loads(text, source, loader=loader, max_depth=max_depth, max_nodes=max_nodes)


@overload
def dump(data: Any, stream: None = None, **kwargs: Any) -> str: ...
@overload
def dump(data: Any, stream: IO[str], **kwargs: Any) -> None: ...


def dump(data: Any, stream: IO[str] | None = None, **kwargs: Any) -> str | None:
    """``yaml.safe_dump`` that writes repeated objects out instead of as anchors and aliases,
    which :func:`loads` refuses."""
    return yaml.dump(data, stream, Dumper=_NoAliasDumper, **kwargs)
