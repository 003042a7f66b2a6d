"""YAML of the user's files (bench configs, sensor specs, acceptance thresholds): one loader and one
dumper, so a number reads the same in every file.

PyYAML's ``safe_load`` follows YAML 1.1, where a float needs a decimal point and a signed exponent:
``1e6``, ``1e-3``, ``1.5e3`` and ``-.5`` are read there as *text*, and a field that wants a number
then refuses them. ``Loader`` is ``yaml.SafeLoader`` with the float syntax of YAML 1.2 (a
superset: every YAML 1.1 float, ``.inf``, ``.nan`` and ``1_000.5`` included, still reads as
before); nothing else (ints, bools, nulls, timestamps) changes. ``Dumper`` is ``yaml.SafeDumper``
with the same resolver, so text such as ``'1e6'`` is written quoted and reads back as text.
"""

from __future__ import annotations

import re

import yaml

FLOAT_TAG = "tag:yaml.org,2002:float"

#: Floats as YAML 1.2 writes them (exponent without a decimal point, unsigned exponent, a sign
#: before a leading ``.``), plus YAML 1.1's sexagesimal floats (``190:20:30.15``) as before.
FLOAT_RE = re.compile(r"""^(?:[-+]?[0-9][0-9_]*\.[0-9_]*(?:[eE][-+]?[0-9]+)?
                          |[-+]?[0-9][0-9_]*[eE][-+]?[0-9]+
                          |[-+]?\.[0-9][0-9_]*(?:[eE][-+]?[0-9]+)?
                          |[-+]?[0-9][0-9_]*(?::[0-5]?[0-9])+\.[0-9_]*
                          |[-+]?\.(?:inf|Inf|INF)
                          |\.(?:nan|NaN|NAN))$""", re.X)


def _with_yaml12_floats(resolvers: dict) -> dict:
    """``resolvers`` (first character -> [(tag, regexp)]) with ``FLOAT_RE`` in place of the float one."""
    return {first: [(tag, FLOAT_RE if tag == FLOAT_TAG else regexp) for tag, regexp in pairs]
            for first, pairs in resolvers.items()}


class Loader(yaml.SafeLoader):
    """``yaml.SafeLoader`` reading YAML 1.2 floats (``1e6`` is 1000000.0, not the text '1e6'), that
    refuses a key given twice in one mapping (PyYAML keeps the last, and a limit written twice
    was silently the second one)."""

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode) and not any(k.tag == "tag:yaml.org,2002:merge" for k, _ in node.value):
            seen = set()
            for key_node, _ in node.value:
                key = self.construct_object(key_node, deep=deep)
                if isinstance(key, (str, int, float, bool)) or key is None:
                    if key in seen:
                        raise yaml.constructor.ConstructorError(
                            None, None, f"duplicate key {key!r}: give each key once", key_node.start_mark)
                    seen.add(key)
        return super().construct_mapping(node, deep)


class Dumper(yaml.SafeDumper):
    """``yaml.SafeDumper`` that quotes text ``Loader`` would read as a float (``'1e6'``)."""


Loader.yaml_implicit_resolvers = _with_yaml12_floats(yaml.SafeLoader.yaml_implicit_resolvers)
Dumper.yaml_implicit_resolvers = _with_yaml12_floats(yaml.SafeDumper.yaml_implicit_resolvers)


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
    """``text`` parsed like ``yaml.safe_load``, with YAML 1.2 floats; ``yaml.YAMLError`` if bad."""
    return yaml.load(text, Loader=Loader)  # noqa: S506 (Loader is a SafeLoader)


def dump_yaml(data, **options) -> str:
    """``data`` as YAML text like ``yaml.safe_dump(data, **options)``, readable by ``load_yaml``."""
    return yaml.dump(data, Dumper=Dumper, **options)
