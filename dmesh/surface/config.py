"""Settings of the surface step (`dmesh.surface`): one frozen section per stage that has settings, and the
run-wide fields. Imports nothing but the standard library, so the run configs (`dmesh.recon.config`) can hold a
`SurfaceConfig` and stay cheap to import.

Units, as each field's comment says: counts (faces, edges, neighbours, rounds), fractions, edge lengths (of the
surface's own mesh) or sample spacings (of the input points); never absolute lengths.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Mapping


def _check(owner: str, name: str, value, ok: bool, want: str) -> None:
    """ValueError naming the field when `ok` is false."""
    if not ok:
        raise ValueError(f"SurfaceConfig.{owner}.{name} must be {want}, got {value!r}")


def _at_least(section, low, *names) -> None:
    for name in names:
        value = getattr(section, name)
        _check(type(section).NAME, name, value, value >= low, f">= {low}")


def _fraction(section, *names) -> None:
    for name in names:
        value = getattr(section, name)
        _check(type(section).NAME, name, value, 0.0 <= value <= 1.0, "in [0, 1]")


@dataclass(frozen=True)
class Vote:
    """Inside/outside vote over the tets (`dmesh.solid.walk_votes`, `drop_open_regions`)."""

    NAME = "vote"
    directions: int = 9          # walks per tet to the hull (counts); odd: no ties
    max_open: float = 0.25       # a region of inside tets whose boundary is more than this fraction non-mesh faces
                                 # (by area) is an open part seen as a volume, not a solid
    min_thickness: float = 0.5   # ... and one thinner than this many mean edge lengths is a pocket in a sheet
    sign_neighbours: int = 3     # input normals nearest each vertex of a mesh face, summed to sign it (winding vote)

    def __post_init__(self):
        _at_least(self, 1, "directions", "sign_neighbours")
        _fraction(self, "max_open")
        _at_least(self, 0.0, "min_thickness")


@dataclass(frozen=True)
class Revote:
    """Second vote without the open sheets that fooled the first (`dmesh.solid.open_sheet_walls`)."""

    NAME = "revote"
    min_faces: int = 64          # an open piece of more than this many faces can be set aside (counts)
    max_open: float = 0.25       # a piece is open when the disk its rim could span is over this fraction of its area
    max_boundary: float = 0.1    # ... and it is set aside with at most this fraction of its area on the
                                 # inside/outside boundary

    def __post_init__(self):
        _at_least(self, 0, "min_faces")
        _fraction(self, "max_open", "max_boundary")


@dataclass(frozen=True)
class Pinches:
    """Tets flipped until the inside/outside boundary is 2-manifold (`dmesh.solid.repair_pinches`)."""

    NAME = "pinches"
    rounds: int = 20             # rounds of flips at most (counts)

    def __post_init__(self):
        _at_least(self, 0, "rounds")


@dataclass(frozen=True)
class Lids:
    """Large holes of the closed part closed by the inside tets' boundary (`dmesh.solid.large_lids`)."""

    NAME = "lids"
    max_hole: int = 64           # a hole whose rim has more edges than this gets a lid (counts)

    def __post_init__(self):
        _at_least(self, 0, "max_hole")


@dataclass(frozen=True)
class Reopen:
    """Lids, fills and spans the input shows to be holes of the shape, taken out again
    (`dmesh.surface.evidence`; `SurfaceConfig.mode` "auto")."""

    NAME = "reopen"
    ratio: float = 2.0           # a point is seen when a sample lies within this many of that sample's spacings
    share: float = 0.5           # a piece more than this fraction unseen (by area), and larger than a disc of
                                 # `ratio` spacings, is a hole the input shows, and stays open

    def __post_init__(self):
        _at_least(self, 0.0, "ratio")
        _fraction(self, "share")


@dataclass(frozen=True)
class Fills:
    """Small holes of the closed part filled over their own rim (`dmesh.surface.holes.fill_holes`)."""

    NAME = "fills"
    max_hole: int = 64           # holes with at most this many edges are filled (counts)
    retries: int = 3             # a fill crossing the surface is made again without its crossing triangles at most
                                 # this many times, then left open (counts)
    tets: bool = True            # ... and then closed by the inside tets' boundary across it instead, where that
                                 # piece fits the hole (faces of the triangulation: they cross nothing)
    tets_sheets: float = 1e-3    # ... on a closed input only: sheets at most this fraction of all faces
    faired: bool = True          # ... and a hole still open then gets its fill anyway, refined and faired like
                                 # a lid (stage fair, which drops it if it still crosses a face); closed input only

    def __post_init__(self):
        _at_least(self, 0, "max_hole", "retries")
        _fraction(self, "tets_sheets")


@dataclass(frozen=True)
class Spans:
    """Closed-part faces across a stretch the input did not sample (`dmesh.surface.debris.long_faces`)."""

    NAME = "spans"
    ratio: float = 6.0           # a face whose longest edge is over this many median edge lengths is a span,
                                 # faired like a lid (edge lengths; 0: none)

    def __post_init__(self):
        _at_least(self, 0.0, "ratio")


@dataclass(frozen=True)
class Crumbs:
    """Stray sheet pieces (`dmesh.surface.debris.crumb_pieces`, `floating_crumbs`)."""

    NAME = "crumbs"
    max_faces: int = 4           # a crumb: an edge-connected piece of at most this many faces; a sheet part made
                                 # only of crumbs is dropped (counts)
    max_debris: float = 1e-3     # a sheet part of at most this fraction of all the faces beside a closed part is
                                 # dropped whatever its pieces' sizes
    floating: float = 4.0        # beside larger pieces, a crumb farther than this many median edge lengths from
                                 # all of them is dropped (edge lengths) ...
    beside: float = 0.05         # ... unless its centre lies off the plane of the surface nearest it by at most
                                 # this fraction of its distance from it
    floating_max_faces: int = 64  # pieces up to this many faces float apart too when also farther from the larger
                                 # ones than their own bounding-box diagonal (counts)
    plane_neighbours: int = 16   # vertices of the larger pieces whose plane the "beside" test takes (counts)

    def __post_init__(self):
        _at_least(self, 0, "max_faces", "floating_max_faces")
        _at_least(self, 1, "plane_neighbours")
        _fraction(self, "max_debris")
        _at_least(self, 0.0, "floating")


@dataclass(frozen=True)
class Stacked:
    """Small sheet pieces lying on a larger surface: stray copies of it (`dmesh.surface.debris.stacked_pieces`)."""

    NAME = "stacked"
    within: float = 1.0          # a piece whose every face lies over a larger piece within this many local edge
                                 # lengths is dropped (edge lengths; 0: none)
    max_faces: int = 64          # largest piece tested (counts)
    neighbours: int = 16         # nearest faces (by centroid) each face is measured against; their median longest
                                 # edge is the local edge length (counts)
    over: float = 0.1            # "over" a face: the closest point at most this many local edge lengths aside
                                 # from the foot of the perpendicular (edge lengths)
    spacings: float = 3.0        # with input samples, the local edge length is at most this many local sample
                                 # spacings (sample spacings, `SurfaceConfig.spacing_neighbours`)

    def __post_init__(self):
        _at_least(self, 0.0, "within", "over", "spacings")
        _at_least(self, 0, "max_faces")
        _at_least(self, 1, "neighbours")


@dataclass(frozen=True)
class WindSheets:
    """Sheets wound consistently and turned to the input normals (`dmesh.surface.winding.orient_sheets`)."""

    NAME = "wind_sheets"
    neighbours: int = 10         # input normals averaged per face (counts)
    confident: float = 0.5       # a face agrees with its normals when the cosine is at least this; a piece turns
                                 # by its area-weighted mean agreement when that is at least half of it (fraction)
    turn_faces: bool = True      # a face of a sheet that cannot be wound consistently turns on its own when its
                                 # normals clearly disagree (False: whole sheets only, for vectors that are not
                                 # normals, e.g. towards cameras)

    def __post_init__(self):
        _at_least(self, 1, "neighbours")
        _fraction(self, "confident")


@dataclass(frozen=True)
class SheetHoles:
    """Small inner holes of the sheets filled where the input sampled across them
    (`dmesh.surface.holes.sheet_hole_loops`, `sampled_loops`)."""

    NAME = "sheet_holes"
    max_edges: int = 24          # holes with at most this many edges (and as many of the piece's mean edge
                                 # lengths) are filled, never a piece's rim (counts; 0: none)
    max_share: float = 0.25      # ... and with an area of at most this fraction of their piece's
    gap: float = 8.0             # ... and only where the loop's centre lies within this many local sample spacings
                                 # of an input point (sample spacings, `SurfaceConfig.spacing_neighbours`; 0: no test)
    stray_off: float = 0.3       # ... and no loop vertex lies more than this many of its neighbours' mean distances
                                 # off their plane (neighbour spacings; inf: no test)
    stray_neighbours: int = 16   # mesh vertices whose plane the stray test takes (counts)
    retries: int = 3             # a fill crossing the surface is made again at most this many times (counts)

    def __post_init__(self):
        _at_least(self, 0, "max_edges", "retries")
        _at_least(self, 1, "stray_neighbours")
        _fraction(self, "max_share")
        _at_least(self, 0.0, "gap", "stray_off")


@dataclass(frozen=True)
class ClosedCrumbs:
    """Tiny closed pieces beside a larger one (`dmesh.surface.debris.closed_crumb_pieces`)."""

    NAME = "closed_crumbs"
    max_faces: int = 4           # a closed piece of at most this many faces beside a larger one is dropped (counts)

    def __post_init__(self):
        _at_least(self, 0, "max_faces")


@dataclass(frozen=True)
class Copies:
    """Copies of a split vertex moved apart (`dmesh.surface.finish.separate_copies`)."""

    NAME = "copies"
    separation: float = 0.05     # each copy moves this fraction of the way to the mean centroid of its faces

    def __post_init__(self):
        _check(self.NAME, "separation", self.separation, 0.0 <= self.separation < 1.0, "in [0, 1)")


@dataclass(frozen=True)
class Fair:
    """Lids and spans refined and faired (`dmesh.native.refine_and_fair`), folds smoothed
    (`dmesh.surface.crossings.untangle`)."""

    NAME = "fair"
    continuity: int = 1          # fairing continuity at the rim: 0 membrane, 1 thin plate, 2 curvature variation
    density: float = 4.0         # refinement's density control factor (CGAL's default sqrt(2) leaves a large lid
                                 # few new vertices; `python -m studies lids` compares factors)
    untangle_rounds: int = 5     # rounds of smoothing where a faired patch crosses a face (counts)

    def __post_init__(self):
        _check(self.NAME, "continuity", self.continuity, self.continuity in (0, 1, 2), "0, 1 or 2")
        _check(self.NAME, "density", self.density, self.density > 0, "positive")
        _at_least(self, 0, "untangle_rounds")


#: The stages of the surface step in the order they run, and those that may not be skipped (`skip`).
#: `dmesh.surface.STAGES` pairs each name with its function (and checks the order) at import.
STAGE_NAMES = ("vote", "revote", "pinches", "closed_part", "lids", "fills", "spans", "reopen", "fins", "crumbs", "rim",
               "stacked", "wind_sheets", "sheet_holes", "split_fans", "closed_crumbs", "copies", "fair")
REQUIRED = ("vote", "closed_part", "rim", "wind_sheets")
#: `SurfaceConfig.mode`'s values: which holes the surface step closes.
MODES = ("auto", "closed", "open")

#: The section classes, by field name of `SurfaceConfig` (the name of the stage each belongs to).
SECTIONS = {cls.NAME: cls for cls in (Vote, Revote, Pinches, Lids, Fills, Spans, Reopen, Crumbs, Stacked, WindSheets,
                                      SheetHoles, ClosedCrumbs, Copies, Fair)}


@dataclass(frozen=True)
class SurfaceConfig:
    """Settings of `dmesh.surface.run`: one section per stage with settings (docs/surface.md lists them), and the
    run-wide fields below. A section may be given as a mapping of its fields (as `to_dict` writes it)."""

    vote: Vote = Vote()                      # the inside/outside vote over the tets
    revote: Revote = Revote()                # the second vote, open sheets set aside
    pinches: Pinches = Pinches()             # tets flipped at pinches
    lids: Lids = Lids()                      # large holes closed by the inside tets' boundary
    fills: Fills = Fills()                   # small holes of the closed part filled
    spans: Spans = Spans()                   # long closed-part faces faired like lids
    reopen: Reopen = Reopen()                # lids, fills and spans over holes the input shows, taken out
    crumbs: Crumbs = Crumbs()                # stray sheet pieces dropped
    stacked: Stacked = Stacked()             # stray copies lying on a larger surface dropped
    wind_sheets: WindSheets = WindSheets()   # sheets wound and turned to the normals
    sheet_holes: SheetHoles = SheetHoles()   # small inner holes of sheets filled
    closed_crumbs: ClosedCrumbs = ClosedCrumbs()  # tiny closed pieces dropped
    copies: Copies = Copies()                # copies of split vertices moved apart
    fair: Fair = Fair()                      # lids and spans refined and faired
    seed: int = 0                # rotation of the vote's walk directions
    workers: int = 1             # threads of the k-d tree queries (input normals)
    spacing_neighbours: int = 8  # an input sample's local spacing: its mean distance to this many nearest samples
                                 # (counts), scaled so that its median over the samples is their median
                                 # nearest-neighbour distance (`dmesh.surface.evidence`)
    clean: bool = True           # False: orientation only (the labelling and the sheets' winding), no clean-up
    skip: tuple = ()             # names of stages left out (those `dmesh.surface.STAGES` marks not required)
    mode: str = "auto"           # which holes close: "closed" every hole the stages can close (lids, fills,
                                 # spans, sheet holes); "open" none (the input's boundary is the shape's); "auto"
                                 # those the input shows surface across (`reopen`; without input samples, as
                                 # "closed")

    def __post_init__(self):
        for name, cls in SECTIONS.items():
            value = getattr(self, name)
            if isinstance(value, Mapping):
                object.__setattr__(self, name, _section(cls, value))
            elif not isinstance(value, cls):
                raise TypeError(f"SurfaceConfig.{name} must be a {cls.__name__} or a mapping of its fields, got "
                                f"{type(value).__name__}")
        if int(self.spacing_neighbours) < 1:
            raise ValueError(f"SurfaceConfig.spacing_neighbours must be >= 1, got {self.spacing_neighbours!r}")
        if self.mode not in MODES:
            raise ValueError(f"SurfaceConfig.mode must be one of {', '.join(MODES)}, got {self.mode!r}")
        skip = (self.skip,) if isinstance(self.skip, str) else tuple(self.skip or ())
        object.__setattr__(self, "skip", tuple(str(s) for s in skip))
        if self.skip:
            optional = [s for s in STAGE_NAMES if s not in REQUIRED]
            bad = [s for s in self.skip if s not in optional]
            if bad:
                raise ValueError(f"SurfaceConfig.skip: {', '.join(map(repr, bad))} cannot be skipped; the stages "
                                 f"that may be: {', '.join(optional)}")

    def with_overrides(self, overrides: Mapping[str, Any] | None) -> "SurfaceConfig":
        """A copy with `overrides` applied: dotted keys ("lids.max_hole", "seed", "skip") or nested mappings
        ({"lids": {"max_hole": 100}}). ValueError naming the known sections or fields for an unknown key."""
        top: dict[str, Any] = {}
        nested: dict[str, dict] = {}
        given: dict[str, Any] = {}
        for key, value in dict(overrides or {}).items():
            head, dot, rest = str(key).partition(".")
            if head not in SECTIONS:
                if dot or head not in TOP_FIELDS:
                    raise ValueError(f"SurfaceConfig: unknown key {key!r}; sections: {', '.join(SECTIONS)}; "
                                     f"run-wide fields: {', '.join(TOP_FIELDS)}")
                top[head] = value
            elif dot:
                if "." in rest:
                    raise ValueError(f"SurfaceConfig: key {key!r} is deeper than SECTION.FIELD")
                nested.setdefault(head, {})[rest] = value
            elif isinstance(value, Mapping):
                nested.setdefault(head, {}).update(value)
            elif isinstance(value, SECTIONS[head]):
                given[head] = value
            else:
                raise ValueError(f"SurfaceConfig: {key!r} is a section; give a mapping of its fields or "
                                 f"{key}.FIELD=VALUE, got {value!r}")
        sections = {name: _section(SECTIONS[name], values, given.get(name, getattr(self, name)))
                    for name, values in nested.items()}
        return dataclasses.replace(self, **{**given, **sections}, **top)

    def to_dict(self) -> dict:
        """The settings as plain values (sections as dicts, `skip` as a list); `SurfaceConfig(**d)` rebuilds it."""
        out = dataclasses.asdict(self)
        out["skip"] = list(self.skip)
        return out


#: The run-wide fields of `SurfaceConfig` (the others are its sections).
TOP_FIELDS = tuple(f.name for f in dataclasses.fields(SurfaceConfig) if f.name not in SECTIONS)


def _section(cls, values: Mapping, base=None):
    """`base` (default: `cls()`) with the fields of `values`; ValueError naming the known fields otherwise."""
    known = [f.name for f in dataclasses.fields(cls)]
    unknown = sorted(set(values) - set(known))
    if unknown:
        raise ValueError(f"SurfaceConfig.{cls.NAME} has no field {', '.join(map(repr, unknown))}; its fields: "
                         f"{', '.join(known)}")
    return dataclasses.replace(base if base is not None else cls(), **dict(values))


__all__ = ["SurfaceConfig", "SECTIONS", "TOP_FIELDS", "MODES", *[cls.__name__ for cls in SECTIONS.values()]]
