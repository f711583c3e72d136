"""The gloss reproduction model (thesis chapter 6, section 7.2.1).

  glossrig model crossval --ward WARD.csv --coverages COV.csv --out cv.json
      leave-one-out cross-validation of Table 7.1's three methods, with
      automatic detection of fabrication outliers (the thesis dropped 4/6 by hand)
  glossrig model fit --ward WARD.csv --coverages COV.csv --out model.json
      fit the two bases and the effective-to-nominal sigmoid (eq. 6.1-6.8)
  glossrig model predict --model model.json --ward rho_d=..,rho_s=..,alpha_x=..,alpha_y=..,lobe_rotation=..
      nominal coverage to fabricate for a target material, and its gamut distance

WARD.csv holds the samples' fitted Ward parameters (columns name, rho_d, rho_s,
alpha_x, alpha_y, lobe_rotation in radians: a column beyond 2 pi is refused as
degrees); --ward PARAMS of predict takes lobe_rotation in radians or with a unit
(140deg, 2.44rad); values outside rho_d in [0, 1], rho_s >= 0, rho_d + rho_s <= 1,
alpha in (0, 0.5] (thesis Table 4.2) are refused. COV.csv their nominal coverages (columns
sample, nominal_b2). Sample "0/6" matches Ward row "sample_0_6".
"""
from __future__ import annotations

import json
import logging
import time
from pathlib import Path

from glossrig.cli.outputs import add_force_option, prepare_output
from glossrig.cli.verbs import SubVerb
from glossrig.core.atomic import atomic_write_text
from glossrig.core.errors import InputError

_log = logging.getLogger(__name__)

HELP = "reproduction model: cross-validate, fit, predict the nominal coverage (thesis ch. 6)"


def _add_data_args(p) -> None:
    p.add_argument("--ward", required=True, metavar="CSV",
                   help="samples' Ward parameters (thesis Table 9.1 layout; lobe_rotation column in radians)")
    p.add_argument("--coverages", required=True, metavar="CSV",
                   help="samples' nominal coverages, column nominal_b2 (thesis Table 6.2)")
    p.add_argument("--exclude", default="auto", metavar="auto|none|NAMES",
                   help="samples left out of the fit: 'auto' = detected fabrication outliers (default), "
                        "'none', or comma-separated names such as 4/6")
    p.add_argument("--rig", default=None, metavar="TOML", help="rig description (default: scenes/thesis_rig.toml)")
    p.add_argument("--scale", type=float, default=None,
                   help="camera image scale for the measurement angles (default 0.05)")
    p.add_argument("--max-angles", type=int, default=None,
                   help="subsample the measurement angles to at most this many (default 12000)")
    p.add_argument("--starts", type=int, default=3,
                   help="deterministic starting points of the base-2 fit per model (default 3)")
    p.add_argument("--out", required=True, metavar="JSON", help="output file")
    add_force_option(p, "an existing --out file")


def _add_fit_args(p) -> None:
    _add_data_args(p)
    p.add_argument("--no-clip", action="store_true", help="do not clip BRDF values at 1.0 (eq. 6.5)")


def _add_predict_args(p) -> None:
    p.add_argument("--model", required=True, metavar="JSON", help="model written by 'glossrig model fit'")
    p.add_argument("--ward", required=True, metavar="PARAMS",
                   help="target: rho_d=..,rho_s=..,alpha_x=..,alpha_y=..[,lobe_rotation=..]; lobe_rotation in "
                        "radians, or with a unit (140deg, 2.44rad); rho_d in [0, 1], rho_s >= 0, "
                        "rho_d + rho_s <= 1, alpha in (0, 0.5] (thesis Table 4.2)")
    p.add_argument("--json", action="store_true", help="print the prediction as JSON")


def _progress(t0: float):
    def say(msg: str) -> None:
        _log.info(f"[{time.monotonic() - t0:6.1f} s] {msg}")
    return say


def _exclude(spec: str, samples):
    s = spec.strip()
    if s == "auto":
        return None
    if s == "none":
        return []
    names = [n.strip() for n in s.split(",") if n.strip()]
    if not names:
        raise InputError(f"--exclude: expected 'auto', 'none' or sample names, got {spec!r}")
    for n in names:
        samples.index(n)          # unknown sample -> InputError
    return names


def _starts(args) -> int:
    if args.starts < 1:
        raise InputError(f"--starts must be >= 1, got {args.starts}")
    return args.starts


def _check_out(args) -> Path:
    """--out may be written (glossrig.cli.outputs): checked before any work."""
    return prepare_output(args.out, args.force)


def _write_json(path: Path, data: dict | str) -> None:
    """Write atomically: a failed or interrupted run leaves any earlier file intact."""
    text = data if isinstance(data, str) else json.dumps(data, indent=1) + "\n"
    try:
        atomic_write_text(path, text)
    except OSError as e:
        raise InputError(f"cannot write: {e.strerror}", path=path) from None


def _angles(args):
    from glossrig.core.reproduction import model as R
    kw = {}
    if args.scale is not None:
        kw["scale"] = args.scale
    if args.max_angles is not None:
        kw["max_samples"] = args.max_angles
    return R.rig_angles(args.rig, **kw)


def _crossval(args) -> int:
    from glossrig.core.reproduction import model as R
    out = _check_out(args)
    samples = R.load_samples(args.ward, args.coverages)
    exclude = _exclude(args.exclude, samples)
    t0 = time.monotonic()
    say = _progress(t0)
    angles = _angles(args)
    say(f"{len(samples)} samples, {len(angles)} measurement angle sets")
    res = R.cross_validate(samples, angles, exclude=exclude, progress=say, n_starts=_starts(args))
    res["inputs"] = {"ward": str(args.ward), "coverages": str(args.coverages)}
    res["seconds"] = round(time.monotonic() - t0, 1)
    _write_json(out, res)
    print(f"outliers ({'detected' if exclude is None else 'given'}): {', '.join(res['outliers']) or 'none'}")
    print("method  used samples                         preprocessing     error mean  error std")
    for m in res["methods"]:
        used = "all" if not m["excluded"] else "all but " + ", ".join(m["excluded"])
        print(f"{m['method']:>6}  {used:<36} {m['preprocessing']:<17} {m['error_mean']:10.3f} {m['error_std']:10.3f}")
    print(f"wrote {out}")
    return 0


def _fit(args) -> int:
    from glossrig.core.reproduction import model as R
    out = _check_out(args)
    samples = R.load_samples(args.ward, args.coverages)
    exclude = _exclude(args.exclude, samples)
    t0 = time.monotonic()
    say = _progress(t0)
    angles = _angles(args)
    clip = None if args.no_clip else R.CLIP_LEVEL
    model = R.fit_excluding_outliers(samples, angles, clip, exclude, progress=say, n_starts=_starts(args))
    data = model.to_json()
    data["fit"]["inputs"] = {"ward": str(args.ward), "coverages": str(args.coverages)}
    _write_json(out, R.dumps_model(data))
    b2 = model.base2
    print(f"excluded: {', '.join(model.fit_info['excluded']) or 'none'} ({model.fit_info['exclusion']})")
    print(f"base 1 = {model.base1_name}; base 2: rho_d={b2.rho_d:.4f} rho_s={b2.rho_s:.4f} alpha_x={b2.alpha_x:.4f} "
          f"alpha_y={b2.alpha_y:.4f} lobe_rotation={b2.lobe_rotation:.3f}")
    print("ETN: " + data["etn"]["form"] + "  gamma = " + ", ".join(f"{g:.6g}" for g in model.etn.gamma))
    print("sample   nominal  effective  ETN(effective)")
    for t in model.training:
        print(f"{t['sample']:<8} {t['nominal_b2']:7.3f} {t['effective_b2']:10.3f} {t['etn_nominal_b2']:15.3f}")
    print(f"wrote {out}")
    return 0


def _predict(args) -> int:
    from glossrig.core.reproduction import model as R
    from glossrig.core.models.ward import WardParams

    model = R.ReproductionModel.load(args.model)
    target = WardParams.parse(args.ward)
    pr = model.predict(target)
    if args.json:
        print(json.dumps(pr.to_json(), indent=1))
    else:
        print(f"nominal coverage (base 2, scratched area fraction): {pr.nominal_b2:.3f}")
        print(f"nominal coverage of base 1 (unscratched): {pr.nominal_b1:.3f}")
        print(f"effective coverage (base 2): {pr.effective_b2:.3f}")
        print(f"distance of the best mix from the target: rms {pr.rms_distance:.4g} /sr, relative {pr.relative_distance:.3f}"
              f" = {pr.gamut_ratio:.2f} x the training samples' largest ({pr.gamut_threshold:.3f})")
        print(f"gamut: {pr.gamut}")
    if pr.gamut != "in":
        _log.warning(f"target is {'near' if pr.gamut == 'near' else 'out of'} the gamut: "
                     f"the best achievable mix is {pr.gamut_ratio:.2f} x further from it than any fabricated sample "
                     "is from the model")
    return 0


SUBVERBS = (
    SubVerb("crossval", "leave-one-out cross-validation of Table 7.1's three methods", _add_data_args, _crossval),
    SubVerb("fit", "fit bases and ETN sigmoid, write model.json", _add_fit_args, _fit),
    SubVerb("predict", "nominal coverage to fabricate for a target's Ward parameters", _add_predict_args, _predict),
)
