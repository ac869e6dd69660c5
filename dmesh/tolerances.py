"""Numeric tolerances of the library, one name per meaning.

Two kinds: floors that keep a division finite on degenerate input (a zero length, area or sum), and
thresholds that decide whether an input is degenerate (coincident points, collinear triples, parallel
vectors). The fast code and the torch references share them, so both decide alike.
"""

#: Smallest denominator (squared length units of a unit domain) before `dmesh.geometry` clamps it:
#: orthocentres, bisector planes and dual lines of degenerate tets and faces stay finite.
GEOMETRY_EPS = 1e-18

#: Floor of a length, norm or weight sum that divides: normalising normals, weighted means over faces and
#: aspect ratios give finite values on zero-length vectors and empty sums.
DIVISION_FLOOR = 1e-12

#: Floor of a float64 length or area that divides in mesh clean-up (face normals, orientation votes):
#: small enough to leave every nonzero value as it is.
FLOAT64_FLOOR = 1e-300

#: Floor of a per-point gradient norm before the clip divides by it (`dmesh.recon.optim.clip_per_point`).
GRAD_NORM_FLOOR = 1e-30

#: Distance below which two points are the same point (an inserted point on a mesh vertex).
COINCIDENT = 1e-9

#: Squared sine of a triangle's angle, |e1 x e2|^2 / (|e1|^2 |e2|^2), below which its vertices count as
#: collinear (the triple has no dual line).
COLLINEAR = 1e-12

#: Norm of u x axis below which a unit vector u counts as parallel to the axis (pick another axis).
PARALLEL = 1e-6

#: Largest absolute input coordinate accepted. Before an input is normalised, its coordinates are squared
#: (distances), cubed (volumes) and raised to the fourth power (a cross product in a norm: areas) in float64,
#: whose range ends near 1.8e308: at 1e75 a fourth power is 1e300, still finite.
MAX_COORDINATE = 1e75

#: Ratio of an input's second to first principal extent below which its points count as lying on a line (no
#: surface to reconstruct); the sine of `COLLINEAR`.
LINE_RATIO = 1e-6

__all__ = ["GEOMETRY_EPS", "DIVISION_FLOOR", "FLOAT64_FLOOR", "GRAD_NORM_FLOOR", "COINCIDENT", "COLLINEAR",
           "PARALLEL", "MAX_COORDINATE", "LINE_RATIO"]
