"""Scene items as the refined meshes they stand for, and the bubble ids that go with them.

An item is a :class:`~bubsub.core.projection.mesh.Mesh` (3D), a
:class:`~bubsub.core.projection.mesh.Polygon` (2D) or anything with a
``fine()`` method returning one (a
:class:`~bubsub.core.projection.subdivision.SubdivisionSurface`).
"""

from __future__ import annotations

import numbers

from bubsub.core.projection.mesh import Mesh, Polygon

__all__ = ["resolve_items", "bubble_ids"]


def resolve_items(items, want, what, hint=""):
    """Items as a list of ``want`` (Mesh or Polygon); subdivision surfaces are refined.

    Parameters
    ----------
    items : item or sequence of items
        One item is taken as a list of one.
    want : type
        ``Mesh`` or ``Polygon``.
    what : str
        The argument's name in error messages (``"meshes"``).
    hint : str
        Appended to the message about an item of the wrong kind.

    Returns
    -------
    list of ``want``

    Raises
    ------
    ValueError
        If ``items`` is no sequence, or an item is not (or does not refine to) a ``want``.
    """
    if isinstance(items, (Mesh, Polygon)) or hasattr(items, "fine"):
        items = [items]
    try:
        items = list(items)
    except TypeError:
        raise ValueError(f"{what} must be a sequence of {want.__name__}, got {type(items).__name__}") from None
    out = []
    for i, it in enumerate(items):
        if not isinstance(it, (Mesh, Polygon)) and hasattr(it, "fine"):
            it = it.fine()
        if not isinstance(it, want):
            raise ValueError(f"{what}[{i}] is a {type(it).__name__}, expected a {want.__name__}{hint}")
        out.append(it)
    return out


def bubble_ids(ids, n):
    """Checked bubble ids for ``n`` bubbles: ``0..n-1`` by default, else ``n`` unique integers.

    Parameters
    ----------
    ids : sequence of int or None
    n : int

    Returns
    -------
    list of int

    Raises
    ------
    ValueError
        On a count other than ``n``, a non-integer (booleans included) or a repeated id.
    """
    if ids is None:
        return list(range(n))
    try:
        ids = list(ids)
    except TypeError:
        raise ValueError(f"ids must be a sequence of integers, got {type(ids).__name__}") from None
    if len(ids) != n:
        raise ValueError(f"ids has {len(ids)} entries but there are {n} bubbles")
    out = []
    for i in ids:
        if isinstance(i, bool) or not isinstance(i, numbers.Integral):
            raise ValueError(f"ids must be integers, got {i!r}")
        out.append(int(i))
    if len(set(out)) != len(out):
        raise ValueError("ids must be unique")
    return out
