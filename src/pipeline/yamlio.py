"""A strict reader of a lab's YAML files (dataset.yaml, site.yaml, water.yaml).

PyYAML keeps the last of two equal keys without a word, and reads an unquoted
value by YAML 1.1's rules: ``serial: 0123`` becomes the octal number 83, ``make:
no`` the boolean False.  :func:`load_yaml` refuses a duplicate key (its
:class:`DuplicateKey` names the key and both lines) and reads the plain scalars at
the paths a caller declares to be text exactly as they are written.
"""

from __future__ import annotations

from collections.abc import Iterable

import yaml

__all__ = ["KEYS", "DuplicateKey", "load_yaml"]

#: in a text path, the keys of the mapping at that point (e.g. the lens names of ``lenses``)
KEYS = object()
#: in a text path, every value of the mapping at that point
ANY = "*"
_STR_TAG = "tag:yaml.org,2002:str"


class DuplicateKey(yaml.YAMLError):
    """A mapping holds the same key twice: the key, and the (1-based) lines of both."""

    def __init__(self, key, line: int, first_line: int):
        super().__init__(f"key {key!r} appears twice (lines {first_line} and {line})")
        self.key = key
        self.line = line
        self.first_line = first_line


class _StrictLoader(yaml.SafeLoader):
    """The safe loader, refusing a mapping with two equal keys."""

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode):
            seen: dict = {}
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue
                key = self.construct_object(key_node, deep=True)
                try:
                    first = seen.get(key)
                except TypeError:        # an unhashable key: the constructor below names it
                    break
                line = key_node.start_mark.line + 1
                if first is not None:
                    raise DuplicateKey(key, line, first)
                seen[key] = line
        return super().construct_mapping(node, deep=deep)


def _as_written(node) -> None:
    """A plain (unquoted) scalar read as its text, whatever YAML 1.1 would have made of it."""
    if isinstance(node, yaml.ScalarNode) and node.style is None and node.tag != _STR_TAG:
        node.tag = _STR_TAG


def _mark_text(node, path: tuple) -> None:
    if not path or not isinstance(node, yaml.MappingNode):
        if not path:
            _as_written(node)
        return
    step, rest = path[0], path[1:]
    for key_node, value_node in node.value:
        if step is KEYS:
            _as_written(key_node)
        elif step == ANY or (isinstance(key_node, yaml.ScalarNode) and key_node.value == step):
            _mark_text(value_node, rest)


def load_yaml(text: str, text_paths: Iterable[tuple] = ()):
    """The document in ``text``; a YAMLError (a :class:`DuplicateKey` among them) when it is not valid.

    Parameters
    ----------
    text : str
        The YAML text of one document.
    text_paths : iterable of tuple, optional
        Key paths, e.g. ``("camera", "serial")`` or ``("lenses", KEYS)``, whose plain (unquoted) scalars are
        read as the text written (``0123`` stays '0123', ``no`` stays 'no'); a step :data:`KEYS` marks the keys
        of the mapping at that point, a step ``"*"`` every value of it. Default none.

    Returns
    -------
    object
        The parsed document (dict, list or scalar), or None for an empty document.

    Raises
    ------
    DuplicateKey
        When a mapping holds the same key twice (the key and both 1-based lines are named).
    yaml.YAMLError
        When the text is not valid YAML.
    """
    loader = _StrictLoader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        for path in text_paths:
            _mark_text(node, tuple(path))
        return loader.construct_document(node)
    finally:
        loader.dispose()
