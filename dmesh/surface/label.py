"""Stages that label the tets inside or outside and take the closed part from the labelling (`dmesh.solid` holds
the geometry of each: walks, open regions, sheets set aside, pinches, the oriented boundary)."""
from __future__ import annotations

import numpy as np

from dmesh import solid


def vote(state, cfg):
    """Each mesh face gets the side its nearest input normals point to (a winding vote; without normals, a
    parity vote), walks from every tet to the hull count the faces they cross, and regions of inside tets
    that are open parts or pockets are set outside."""
    pd, walls = state.pd, state.walls
    if state.normals is not None:
        state.sign = solid.wall_signs(pd, walls, *state.normals, k=cfg.sign_neighbours, workers=state.workers)
    state.dirs, state.vote = solid.directions(cfg.directions, state.seed), cfg
    votes = solid.walk_votes(pd, walls, state.dirs, state.sign)
    state.inside, dropped = solid.drop_open_regions(pd, walls, votes > 0.5, cfg.max_open, cfg.min_thickness)
    state.info.update(vote="parity" if state.sign is None else "winding", regions_dropped=dropped)
    return state


def revote(state, cfg):
    """Large open pieces the vote left off the inside/outside boundary (a sheet over a solid, which makes walks
    count two walls) are set aside and the vote is taken again, with its own settings, without them."""
    pd, walls = state.pd, state.walls
    aside = solid.open_sheet_walls(pd, walls, state.inside, cfg.max_open, cfg.min_faces, cfg.max_boundary)
    if aside.any():
        solids = walls & ~aside
        if solids.any():
            votes = solid.walk_votes(pd, solids, state.dirs, state.sign)
            state.inside, state.info["regions_dropped"] = solid.drop_open_regions(
                pd, solids, votes > 0.5, state.vote.max_open, state.vote.min_thickness)
        else:  # only sheets: nothing is inside
            state.inside = np.zeros_like(state.inside)
    state.info["sheets_set_aside"] = int(aside.sum())
    return state


def pinches(state, cfg):
    """Tets are flipped, smallest group first, until the inside/outside boundary has no non-manifold edge or
    vertex."""
    state.inside, state.info["tets_flipped"] = solid.repair_pinches(state.pd, state.inside, cfg.rounds)
    return state


def closed_part(state, cfg):
    """The mesh faces between an inside and an outside tet, wound from the inside one to the outside one, are the
    closed part; the other mesh faces are the sheets."""
    pd, walls, inside = state.pd, state.walls, state.inside
    state.between = solid.boundary_mask(pd, inside)
    closed = solid.oriented_boundary(pd, inside, np.flatnonzero(walls & state.between))
    state.set_faces(closed, pd.faces[walls & ~state.between].astype(np.int64))
    state.info.update(inside_tets=int(inside.sum()), closed_faces=int(len(closed)))
    return state


__all__ = ["vote", "revote", "pinches", "closed_part"]
