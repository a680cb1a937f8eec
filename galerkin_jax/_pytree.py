"""Frozen dataclasses as pytree nodes whose structure records their class.

``jax.tree_util.register_dataclass`` is not used: in jaxlib 0.10.2 the PyTreeDefs of two
such nodes compare equal when only their classes differ (``CG(1, rule)`` and ``DG(1, rule)``),
although their hashes differ. A cache keyed by tree structure, such as the one ``jax.jit``
keeps of its traces, then serves the trace of one class to the other whenever the two keys
meet in a hash bucket: in some processes every dG(1) step silently ran as cG(1). Nodes
registered with ``register_pytree_with_keys`` compare their classes.
"""

import dataclasses
import functools

import jax


def pytree_dataclass(cls) -> type:
    """``cls`` as a frozen dataclass and a pytree node.

    Fields with ``metadata={"static": True}`` are auxiliary data (hashed, compared, part of
    the tree structure: a new value means a new compilation); the others are children.
    Unflattening calls the dataclass's ``__init__``, so ``__post_init__`` runs on every rebuilt
    node, whose children may be tracers, cotangents, tree-map results or the objects JAX puts
    in axis specs: it may check static fields only.

    A class may define ``_check_on_construction(self)``: it runs after ``__init__`` when the
    user constructs the node (``cls(...)``, ``dataclasses.replace``), not when JAX rebuilds it,
    so it may check the values of the children the user gave (where they are concrete).
    """
    cls = dataclasses.dataclass(frozen=True)(cls)
    init = cls.__init__
    check = getattr(cls, "_check_on_construction", None)
    if check is not None:

        @functools.wraps(init)
        def checked_init(self, *args, **kwargs):
            init(self, *args, **kwargs)
            check(self)

        cls.__init__ = checked_init
    fields = dataclasses.fields(cls)
    static = tuple(f.name for f in fields if f.metadata.get("static", False))
    children = tuple(f.name for f in fields if not f.metadata.get("static", False))
    keys = tuple(jax.tree_util.GetAttrKey(name) for name in children)

    def flatten(node):
        return tuple(getattr(node, name) for name in children), tuple(getattr(node, name) for name in static)

    def flatten_with_keys(node):
        leaves, aux = flatten(node)
        return tuple(zip(keys, leaves)), aux

    def unflatten(aux, leaves):
        node = object.__new__(cls)
        init(node, **dict(zip(static, aux)), **dict(zip(children, leaves)))  # without the construction check
        return node

    jax.tree_util.register_pytree_with_keys(cls, flatten_with_keys, unflatten, flatten)
    return cls
