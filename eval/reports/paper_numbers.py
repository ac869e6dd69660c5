"""Published numbers of the DMesh paper (Son et al., NeurIPS 2024), transcribed from
`../shared/reference/dmesh_paper.txt`, for side columns in the reports. Never computed here.

Units: Chamfer distances in raw units (the paper prints them x1e-3: CD based on the L1 norm, i.e. the mean
unsigned distance summed over both directions, in the frame with vertex mean 0 and max vertex norm 1);
times in seconds; RE / FP as fractions (the paper prints percentages).
"""
from __future__ import annotations

#: Table 2 of the paper, "Statistics for Point Cloud (PC) and Multi-View (MV) Reconstruction":
#: CD (10^-3, here converted to raw units) per class, and the mean time per model in seconds.
#: The paper's shapes: 4 closed (Thingi32), 4 open (DeepFashion3D), 3 mixed (Objaverse / Adobe Stock).
TABLE2: dict[str, dict[str, dict[str, float]]] = {
    "pointcloud": {
        "Ours (DMesh)": {"closed": 7.42e-3, "open": 6.87e-3, "mixed": 8.06e-3, "time_s": 775.05},
        "PSR": {"closed": 7.15e-3, "open": 26.94e-3, "mixed": 67.18e-3, "time_s": 10.61},
        "VoroMesh": {"closed": 7.30e-3, "open": 26.31e-3, "mixed": 99087.64e-3, "time_s": 12.18},
        "NDC": {"closed": 7.30e-3, "open": 6.83e-3, "mixed": 8.25e-3, "time_s": 3.48},
    },
    "multiview": {
        "Ours (DMesh)": {"closed": 15.56e-3, "open": 11.11e-3, "mixed": 18.33e-3, "time_s": 1434.0},
        "Flexicube": {"closed": 31.23e-3, "open": 34.91e-3, "mixed": 25.15e-3, "time_s": 56.47},
        "NIE": {"closed": 31.54e-3, "open": 67.37e-3, "mixed": 43.05e-3, "time_s": 6696.43},
    },
}

#: Notes shown under the published Table 2 of each input kind: the paper's rows we cannot reproduce here.
TABLE2_NOTES: dict[str, tuple[str, ...]] = {
    "pointcloud": ("NDC: not available (pretrained weights not reachable offline)",),
}

#: Table 1 of the paper, "Mesh reconstruction results" (mesh to DMesh on Stanford models, 20K steps):
#: recovery ratio RE and false-positive ratio FP of faces, as fractions.
TABLE1: dict[str, dict[str, float]] = {
    "Bunny": {"RE": 0.9978, "FP": 0.0000},
    "Dragon": {"RE": 0.9972, "FP": 0.0055},
    "Buddha": {"RE": 0.9964, "FP": 0.0084},
}

#: Our method names that correspond to a row of the paper's Table 2 (per input kind).
METHOD_TO_PAPER_ROW: dict[str, str] = {"psr": "PSR", "voromesh": "VoroMesh", "flexicubes": "Flexicube", "nie": "NIE"}


def table2_row(method: str, input_kind: str) -> dict[str, float] | None:
    """The paper's Table 2 row for one of our methods, or None when the paper has no such row.

    DMesh methods (names starting with "dmesh") map to the paper's "Ours" row of their input kind.
    """
    table = TABLE2.get(input_kind, {})
    if method.startswith("dmesh"):
        return table.get("Ours (DMesh)")
    name = METHOD_TO_PAPER_ROW.get(method)
    return table.get(name) if name else None


def table1_row(shape: str) -> tuple[str, dict[str, float]] | None:
    """(paper model name, row) of Table 1 for a shape id that names a Stanford model, else None."""
    s = shape.lower()
    for key, model in (("bun", "Bunny"), ("dragon", "Dragon"), ("buddha", "Buddha")):
        if key in s:
            return model, TABLE1[model]
    return None
