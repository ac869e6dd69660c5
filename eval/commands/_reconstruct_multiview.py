"""`dmesh reconstruct multiview DIR -o OUT.obj`: the multi-view half of `eval.commands.reconstruct`.

DIR is a capture folder written by `dmesh capture` (its `views.npz`: diffuse, depth, mask, cameras). The
output mesh is in the capture's world frame; `OUT.timings.json` beside it holds the seconds per stage, the
config, the per-epoch counts and the final figures. Every file is written under a temporary name and renamed.
(The leading underscore keeps this module out of the subcommand discovery of `eval.cli`.)
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

#: The presets of `dmesh.recon.multiview.PRESETS` (a test checks they agree), listed without importing torch.
PRESET_NAMES = ("fast", "paper", "depth", "refine", "tiny")


def read_capture(directory: str | Path):
    """The `datasets.capture.MultiView` in `directory`; one-line FileNotFoundError / ValueError otherwise."""
    from datasets.capture import MultiView

    d = Path(directory)
    if not d.exists():
        raise FileNotFoundError(f"{d}: no such folder")
    if not d.is_dir():
        raise ValueError(f"{d}: not a folder (give the capture folder written by `dmesh capture`)")
    if not (d / "views.npz").is_file():
        raise ValueError(f"{d}: not a capture folder (no views.npz; write one with `dmesh capture MESH -o {d}`)")
    try:
        return MultiView.load(d)
    except Exception as exc:  # numpy and zipfile raise several types for corrupt or incomplete archives
        msg = " ".join(f"{type(exc).__name__}: {exc}".split())
        raise ValueError(f"{d / 'views.npz'}: cannot read ({msg})") from None


def build_config(preset: str, seed: int, overrides: dict):
    """A `MultiViewConfig` from a preset, the seed and `--set` overrides (ValueError on unknown keys)."""
    from dmesh.recon.multiview import MultiViewConfig
    from eval.commands.reconstruct import config_error

    fields = {f.name for f in dataclasses.fields(MultiViewConfig)}
    unknown = sorted(set(overrides) - fields)
    if unknown:
        raise ValueError(f"unknown config keys {unknown}; known: {sorted(fields)}")
    for key in ("refine_seeds", "steps_phase1", "steps_phase2", "freeze_phase2"):
        if key in overrides and not isinstance(overrides[key], (list, tuple, int)):
            raise ValueError(f"--set {key}= expects an integer or a list like [1, 2], got {overrides[key]!r}")
    try:
        return MultiViewConfig.preset(preset, **{"seed": seed, **overrides})
    except (TypeError, ValueError) as exc:
        raise ValueError(config_error(exc, overrides)) from None


def run_multiview(args, overrides: dict) -> int:
    """The `multiview` kind of `dmesh reconstruct` (args as parsed there; overrides from `--set`)."""
    from dmesh.recon.multiview import reconstruct
    from eval.commands.reconstruct import write_outputs
    from eval.progress import progress

    out = Path(args.out)
    if args.normals or args.steps is not None:
        raise ValueError("--normals and --steps apply to point clouds only (use --set for multi-view steps)")
    cfg = build_config(args.preset, args.seed, overrides)
    views = read_capture(args.input)

    bar = progress(total=cfg.total_steps(), desc="dmesh", unit="step")

    def on_step(rec: dict) -> None:
        if "stage" in rec:
            bar.set_description(f"dmesh {rec['stage']}")
            return
        bar.update(1)
        bar.set_postfix(loss=f"{rec['loss']:.4g}", faces=rec["faces"], refresh=False)

    try:
        res = reconstruct(views, cfg, callback=on_step, state_path=args.state)
    finally:
        bar.close()
    write_outputs(out, res, cfg, {"input": str(args.input), "output": str(out), "kind": "multiview",
                                  "preset": args.preset})
    return 0
