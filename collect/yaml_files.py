"""YAML of the user's files (bench configs, sensor specs, acceptance thresholds): one loader and one
dumper, so a number reads the same in every file.

PyYAML's ``safe_load`` follows YAML 1.1, where a float needs a decimal point and a signed exponent:
``1e6``, ``1e-3``, ``1.5e3`` and ``-.5`` are read there as *text*, and a field that wants a number
then refuses them. ``Loader`` is ``yaml.SafeLoader`` with the float syntax of YAML 1.2 (a
superset: every YAML 1.1 float, ``.inf``, ``.nan`` and ``1_000.5`` included, still reads as
before), and with whole numbers written in decimal alone (``INT_RE``): YAML 1.1's other ones,
``0123`` (octal: 83), ``0x1A``, ``0b11``, ``1_000`` and ``1:30`` (sexagesimal: 90), read as the
text written (until session 51 a device name ``camera_id: 0123`` became '83'; a field that wants a
number refuses them). Bools, nulls and timestamps do not change. ``Dumper`` is ``yaml.SafeDumper``
with the same float resolver, so text such as ``'1e6'`` is written quoted and reads back as text,
and YAML 1.1's int one (``'0123'`` is written quoted too: other readers take YAML 1.1's ints).
"""

from __future__ import annotations

import os
import re
import stat
from pathlib import Path

import yaml

from collect.errors import InputError

FLOAT_TAG = "tag:yaml.org,2002:float"
INT_TAG = "tag:yaml.org,2002:int"
MERGE_TAG = "tag:yaml.org,2002:merge"
#: Values (list items, mapping keys and values) that aliases (``*name``) may add to a file by
#: repeating what an anchor holds. A few nested aliases repeat it exponentially ("billion laughs":
#: 383 bytes read as 4.8 million values, and an error message of 39 MB quoting them).
MAX_ALIAS_VALUES = 10_000
#: Largest YAML file read (bytes): the biggest config, a sensor spec listing every pixel of its
#: image as dead, is about 1 MB (was: ``/dev/zero`` read until memory ran out).
MAX_YAML_BYTES = 16_000_000

#: Floats as YAML 1.2 writes them (exponent without a decimal point, unsigned exponent, a sign
#: before a leading ``.``), plus YAML 1.1's sexagesimal floats (``190:20:30.15``) as before.
FLOAT_RE = re.compile(r"""^(?:[-+]?[0-9][0-9_]*\.[0-9_]*(?:[eE][-+]?[0-9]+)?
                          |[-+]?[0-9][0-9_]*[eE][-+]?[0-9]+
                          |[-+]?\.[0-9][0-9_]*(?:[eE][-+]?[0-9]+)?
                          |[-+]?[0-9][0-9_]*(?::[0-5]?[0-9])+\.[0-9_]*
                          |[-+]?\.(?:inf|Inf|INF)
                          |\.(?:nan|NaN|NAN))$""", re.X)


#: Whole numbers: decimal digits, a sign, no leading zero (YAML 1.2's decimal ints).
INT_RE = re.compile(r"^[-+]?(?:0|[1-9][0-9]*)$")


def _with_plain_numbers(resolvers: dict, ints: bool = True) -> dict:
    """``resolvers`` (first character -> [(tag, regexp)]) with ``FLOAT_RE`` in place of the float
    one, and (``ints``) ``INT_RE`` in place of the int one."""
    swap = {FLOAT_TAG: FLOAT_RE, **({INT_TAG: INT_RE} if ints else {})}
    return {first: [(tag, swap.get(tag, regexp)) for tag, regexp in pairs] for first, pairs in resolvers.items()}


class Loader(yaml.SafeLoader):
    """``yaml.SafeLoader`` reading YAML 1.2 floats (``1e6`` is 1000000.0, not the text '1e6') and
    decimal ints (``0123`` is the text '0123', not 83), that refuses a key given twice in one
    mapping (PyYAML keeps the last, and a limit written twice was silently the second one; also in
    a mapping with a merge key ``<<`` or merged in by one, which until session 51 went unchecked),
    a value that holds itself, and aliases that add more than ``MAX_ALIAS_VALUES`` values."""

    def construct_document(self, node):
        sizes = {}  # by node id: one entry per value written in the file
        added = _expanded_size(node, sizes, set()) - len(sizes)
        if added > MAX_ALIAS_VALUES:
            raise yaml.constructor.ConstructorError(
                None, None, f"its aliases (*name) repeat what their anchors hold into {added} more values, over "
                            f"{MAX_ALIAS_VALUES}; write the values out", node.start_mark)
        return super().construct_document(node)

    def compose_mapping_node(self, anchor):
        """The mapping's node, once its keys are checked: as written, before a merge key (``<<``) of
        it or of a mapping that merges it in changes its list of keys."""
        node = super().compose_mapping_node(anchor)
        seen = set()
        for key_node, _ in node.value:
            if key_node.tag == MERGE_TAG or not isinstance(key_node, yaml.ScalarNode):
                continue  # what a merge key merges in is overridden by the keys given
            key = self.construct_object(key_node)
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"duplicate key {key!r}: give each key once", key_node.start_mark)
            seen.add(key)
        return node


def _children(node: yaml.Node) -> list:
    """The nodes right under ``node``: a list's items, a mapping's keys and values."""
    if isinstance(node, yaml.SequenceNode):
        return list(node.value)
    if isinstance(node, yaml.MappingNode):
        return [item for pair in node.value for item in pair]
    return []


def _expanded_size(node: yaml.Node, sizes: dict, open_nodes: set) -> int:
    """Values under ``node``, itself included, each alias counted as a copy of its anchor's
    (``sizes``: by node id, memoized). ``ConstructorError`` for a value that holds itself (an alias
    within its own anchor's value): no config has one, and each copy of it printed in an error
    message printed the whole value again (a 12 kB file gave a 9.7 MB error line)."""
    if id(node) in open_nodes:
        raise yaml.constructor.ConstructorError(
            None, None, "an alias (*name) inside its own anchor's value: write the values out", node.start_mark)
    if id(node) not in sizes:
        open_nodes.add(id(node))
        sizes[id(node)] = 1 + sum(_expanded_size(child, sizes, open_nodes) for child in _children(node))
        open_nodes.discard(id(node))
    return sizes[id(node)]


class Dumper(yaml.SafeDumper):
    """``yaml.SafeDumper`` that quotes text ``Loader`` would read as a float (``'1e6'``)."""


Loader.yaml_implicit_resolvers = _with_plain_numbers(yaml.SafeLoader.yaml_implicit_resolvers)
# YAML 1.1's ints stay in the dumper's: text such as '0123' is written quoted, as any reader takes it
Dumper.yaml_implicit_resolvers = _with_plain_numbers(yaml.SafeDumper.yaml_implicit_resolvers, ints=False)


def yaml_error_text(err: yaml.YAMLError) -> str:
    """One line saying where and why PyYAML refused a file: ``line L, column C: problem (context)``
    (was, for bench configs and thresholds: PyYAML's first line alone, such as "while parsing a flow
    sequence", naming neither the line nor the problem)."""
    mark = getattr(err, "problem_mark", None)
    problem, context = getattr(err, "problem", None), getattr(err, "context", None)
    what = (f"{problem} ({context})" if problem and context else problem or context) or str(err).splitlines()[0]
    where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
    return where + " ".join(str(what).split())


def load_yaml(text: str):
    """``text`` parsed like ``yaml.safe_load`` by ``Loader`` (YAML 1.2 floats, decimal ints, the checks
    above); ``yaml.YAMLError`` if bad."""
    return yaml.load(text, Loader=Loader)  # noqa: S506 (Loader is a SafeLoader)


def read_yaml_file(path, what: str):
    """The data of the YAML file ``path`` (``load_yaml``), a ``what`` (e.g. "sensor spec"): one-line
    ``InputError`` for a file that cannot be read (missing, a folder, a device, over
    ``MAX_YAML_BYTES``, not UTF-8) or is not valid YAML. A pipe is read (``--sensor <(...)``)."""
    path = Path(path)
    try:
        mode = os.stat(path).st_mode
        if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
            raise InputError(f"cannot read {what} {path}: it is a device, not a file")  # was: /dev/zero read forever
        with open(path, "rb") as f:
            data = f.read(MAX_YAML_BYTES + 1)
        if len(data) > MAX_YAML_BYTES:
            raise InputError(f"cannot read {what} {path}: it is over {MAX_YAML_BYTES // 1_000_000} MB, "
                             "not a config file")
        text = data.decode()
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(f"cannot read {what} {path}: {getattr(err, 'strerror', None) or err}") from None
    try:
        return load_yaml(text)
    except yaml.YAMLError as err:
        raise InputError(f"{what} {path} is not valid YAML: {yaml_error_text(err)}") from None
    except RecursionError:  # PyYAML parses nested blocks recursively (was: a RecursionError traceback)
        raise InputError(f"{what} {path} is not valid YAML: its lists or mappings are nested too deeply") from None


def dump_yaml(data, **options) -> str:
    """``data`` as YAML text like ``yaml.safe_dump(data, **options)``, readable by ``load_yaml``."""
    return yaml.dump(data, Dumper=Dumper, **options)
