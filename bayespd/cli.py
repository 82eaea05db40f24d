"""The ``bayespd`` command: calibrate a model, predict crack ensembles, summarise, demo.

    bayespd calibrate MODEL.py --data DATA.npz --method nuts|svi|laplace|tikhonov --out DIR [--checkpoint CKPT]
    bayespd predict DIR --scene SCENE.py --n 200 [--scheduler ADDRESS]
    bayespd summary DIR
    bayespd demo [--out DIR]

Contracts (the files ``bayespd demo`` writes are examples of both):

* MODEL.py defines ``scene()`` -> a ``bayespd.Scene`` and ``model(scene)`` -> a Pyro model
  ``model(**data)`` with an observed sample site ``y``; for ``--method tikhonov`` also
  ``init()`` -> {parameter: starting value} (the parameters estimated) and optionally
  ``fixed()`` -> {parameter: value} (e.g. the horizon delta).
* DATA.npz holds ``y`` (the observations, shaped as the model's ``y`` site) and any other
  keyword data of the model (e.g. ``mask``).
* SCENE.py defines ``fracture_scene()`` -> a ``bayespd.ensemble.scene.FractureScene``
  whose ``params`` are scalar posterior variables of DIR/posterior.nc.

Outputs: DIR/posterior.nc (calibrate; with --checkpoint CKPT a killed NUTS calibration rerun with
the same command resumes from CKPT/, and gives the uninterrupted run's draws), DIR/ensemble/ (predict: one file per realisation,
ensemble.nc, PNG figures; a re-run resumes). Exit codes: 0 done, 2 usage (a missing file,
a file without the expected function, bad options), 1 a failure while computing.
"""
from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import inspect
import json
import sys
import tempfile
from functools import partial
from pathlib import Path

USAGE, FAILURE = 2, 1
METHODS = ("nuts", "svi", "laplace", "tikhonov")


class UsageError(Exception):
    """Bad input from the command line: exit code 2, the message names the fix."""


def _existing(path, what: str) -> Path:
    p = Path(path)
    if not p.exists():
        raise UsageError(f"{what} {p} does not exist: check the path")
    return p


def load_module(path, name: str):
    """Execute a Python file as a module (registered in sys.modules under ``name``)."""
    path = _existing(path, "the file")
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or path.suffix != ".py":
        raise UsageError(f"{path} is not a Python file (.py)")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
    except SyntaxError as e:
        sys.modules.pop(name)
        raise UsageError(f"{path} line {e.lineno}: {e.msg}: fix the Python syntax there") from None
    except Exception as e:  # the file's own code fails when run
        sys.modules.pop(name)
        raise UsageError(f"running {path} raised {type(e).__name__}: {e}: fix that file (it must run on import "
                         "and define the functions only)") from None
    return module


def _function(module, name: str, signature: str, path, role: str, *args):
    """``module.name``, which must take ``args`` (``signature`` in messages) and return ``role``."""
    f = getattr(module, name, None)
    if not callable(f):
        raise UsageError(f"{path} defines no function {signature}: add one that returns {role} "
                         "(see `bayespd calibrate --help` / `bayespd demo`)")
    try:
        inspect.signature(f).bind(*args)
    except TypeError as e:
        raise UsageError(f"{name}{inspect.signature(f)} in {path} cannot be called as {signature} ({e}): "
                         f"define it as {signature}, returning {role}") from None
    return f


@dataclasses.dataclass(frozen=True)
class FileFunction:
    """A function of a user's file, picklable by path: worker processes load the file
    themselves (a function of a file loaded by path cannot be pickled by reference)."""

    path: str
    name: str
    args: tuple = ()
    keywords: tuple = ()

    def __call__(self, params):
        module = _FILES.get(self.path) or _FILES.setdefault(self.path, load_module(self.path, _module_name(self.path)))
        return getattr(module, self.name)(*self.args, params, **dict(self.keywords))


_FILES: dict = {}


def _module_name(path) -> str:
    return "bayespd_user_" + "".join(c if c.isalnum() else "_" for c in str(Path(path).resolve()))


def load_scene(path):
    """``fracture_scene()`` of SCENE.py, its build made portable to worker processes."""
    from bayespd.ensemble.scene import FractureScene

    path = str(Path(_existing(path, "the scene file")).resolve())
    module = load_module(path, _module_name(path))
    _FILES[path] = module
    scene = _function(module, "fracture_scene", "fracture_scene()", path, "a FractureScene")()
    if not isinstance(scene, FractureScene):
        raise UsageError(f"fracture_scene() in {path} returned {type(scene).__name__}, not a "
                         "bayespd.ensemble.scene.FractureScene")
    build = scene.build
    func = build.func if isinstance(build, partial) else build
    if getattr(func, "__module__", None) == module.__name__:
        args, kw = (build.args, tuple(sorted(build.keywords.items()))) if isinstance(build, partial) else ((), ())
        scene = dataclasses.replace(scene, build=FileFunction(path, func.__qualname__, args, kw))
    return scene


def _load_data(path) -> dict:
    import numpy as np
    import torch

    path = _existing(path, "the data file")
    if path.suffix != ".npz":
        raise UsageError(f"--data must be a .npz file of arrays (y, and e.g. mask), not {path.name}")
    try:
        with np.load(path) as f:
            arrays = {k: f[k] for k in f.files}
    except Exception as e:  # not a zip, truncated, object arrays: numpy, zipfile and zlib raise many kinds
        raise UsageError(f"{path} is not a readable .npz file of numeric arrays ({type(e).__name__}: {e}): "
                         "write it again with np.savez(path, y=..., ...)") from None
    if "y" not in arrays:
        raise UsageError(f"{path} holds {sorted(arrays)} but no array 'y' (the observations): "
                         "save it as np.savez(path, y=..., ...)")
    for k, v in arrays.items():
        if v.dtype.kind not in "biuf":
            raise UsageError(f"array {k!r} of {path} holds {v.dtype} values, not numbers or booleans: "
                             "save it as a numeric (or boolean mask) array")
    return {k: torch.as_tensor(v) if v.dtype == bool else torch.as_tensor(v, dtype=torch.float64)
            for k, v in arrays.items()}


def _check_keywords(model, data: dict, path) -> None:
    """Refuse arrays of DATA.npz that ``model(**data)`` does not take."""
    try:
        parameters = inspect.signature(model).parameters.values()
    except (TypeError, ValueError):  # a callable without a signature: its errors speak later
        return
    if any(p.kind is p.VAR_KEYWORD for p in parameters):
        return
    extra = sorted(set(data) - {p.name for p in parameters})
    if extra:
        raise UsageError(f"{path} holds {extra}, which the model does not take (it takes "
                         f"{sorted(p.name for p in parameters)}): drop them from the file, or add them "
                         "to the keywords of the function model(scene) returns")


def calibrate(args) -> int:
    from bayespd.infer import fit, save

    module = load_module(_existing(args.model, "the model file"), "bayespd_user_model")
    scene = _function(module, "scene", "scene()", args.model, "a bayespd.Scene")()
    data = _load_data(args.data)
    if args.checkpoint is not None and args.method != "nuts":
        raise UsageError(f"--checkpoint saves NUTS chains: use it with --method nuts, not {args.method}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.method == "tikhonov":
        tree = _tikhonov(module, scene, data, args)
    else:
        model = _function(module, "model", "model(scene)", args.model, "a Pyro model", scene)(scene)
        _check_keywords(model, data, args.data)
        options = {"nuts": {"num_samples": args.samples, "num_warmup": args.warmup, "num_chains": args.chains,
                            "checkpoint": args.checkpoint, "checkpoint_every": args.checkpoint_every},
                   "svi": {"num_samples": args.samples, "svi_steps": args.svi_steps},
                   "laplace": {"num_samples": args.samples}}[args.method]
        tree = fit(model, data, args.method, seed=args.seed, scene=scene, progress=not args.quiet, **options)
    save(tree, out / "posterior.nc")
    print(f"wrote {out / 'posterior.nc'} ({args.method}, {tree.attrs.get('wall_time_s', 0):.1f} s)")
    _print_posterior(tree)
    if args.method == "nuts":
        _warn_diagnostics(tree)
    return 0


def _warn_diagnostics(tree) -> None:
    """Print the failed MCMC diagnostics (r_hat, ESS, divergences, ...) of ``summary``."""
    import warnings

    from bayespd.infer import summary as diagnose

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        diagnose(tree)
    for w in caught:
        if issubclass(w.category, UserWarning):
            print(f"warning: {w.message}", file=sys.stderr)


def _tikhonov(module, scene, data, args):
    import numpy as np

    from bayespd.infer.datatree import build_tree
    from bayespd.inverse.least_squares import tikhonov

    init = _function(module, "init", "init()", args.model, "{parameter: starting value}")()
    fixed = module.fixed() if callable(getattr(module, "fixed", None)) else None
    res = tikhonov(scene, data["y"], init, fixed=fixed, mask=data.get("mask"))
    posterior = {k: np.asarray(v, dtype=np.float64).reshape(1, 1, *np.shape(v)) for k, v in res.params.items()}
    return build_tree({"posterior": posterior}, {
        "method": "tikhonov", "wall_time_s": res.wall_time_s, "converged": int(res.converged),
        "residual_rms": res.residual_rms, "settings": json.dumps({"init": init, "fixed": fixed or {}})})


def _print_posterior(tree) -> None:
    import numpy as np

    from bayespd.infer import modes

    post = tree["posterior"]
    print(f"{'parameter':>12} {'mean':>12} {'sd':>12} {'5 %':>12} {'95 %':>12}")
    for k in sorted(post.data_vars):
        v = post[k].values
        if v.ndim != 2:
            continue
        lo, hi = np.quantile(v, [0.05, 0.95])
        print(f"{k:>12} {v.mean():12.5g} {v.std():12.5g} {lo:12.5g} {hi:12.5g}")
    if (table := modes(tree, mixed=True)) is not None:
        print(f"a mixture of {len(table)} modes (fit(..., modes='weighted')):")
        print(table.drop(columns=["laplace_log_mass", "log_mass"], errors="ignore").to_string())


def predict(args) -> int:
    from bayespd.infer import load
    from bayespd.ensemble.predictive import ensemble
    from bayespd.plot import ensemble_figures

    folder = _existing(args.dir, "the calibration folder")
    tree = load(_existing(folder / "posterior.nc", "the posterior (run `bayespd calibrate` first)"))
    scene = load_scene(args.scene)
    store = folder / "ensemble"
    ds = ensemble(tree, scene, args.n, n_mean=args.n_mean, store=store, seed=args.seed,
                  scheduler=args.scheduler, workers=args.workers, device=args.device, progress=not args.quiet)
    figures = ensemble_figures(ds, store)
    print(f"wrote {store / 'ensemble.nc'} and {', '.join(p.name for p in figures)}")
    _print_ensemble(ds)
    return 0


def _print_ensemble(ds) -> None:
    print(f"{ds.attrs['realisations_posterior']} posterior + {ds.attrs['realisations_mean']} mean-parameter "
          f"realisations, {ds.attrs['failed']} failed")
    print(f"{'outcome':>20} {'posterior 5-50-95 %':>34} {'sd total':>10} {'aleatoric':>10} {'epistemic':>10}")
    for name in ds["outcome"].values:
        sd = ds["spread"].sel(outcome=name).values
        q = ds[f"{name}_quantiles"].sel(kind="posterior").values if f"{name}_quantiles" in ds else None
        band = "(across the crack line)" if q is None else " ".join(f"{v:10.4g}" for v in q)
        print(f"{name:>20} {band:>34} {sd[0]:10.4g} {sd[1]:10.4g} {sd[2]:10.4g}")


def summary(args) -> int:
    import xarray as xr

    from bayespd.infer import load

    folder = _existing(args.dir, "the folder")
    posterior, ens = folder / "posterior.nc", folder / "ensemble" / "ensemble.nc"
    if not posterior.exists() and not ens.exists():
        raise UsageError(f"{folder} holds neither posterior.nc nor ensemble/ensemble.nc: "
                         "run `bayespd calibrate` (and `bayespd predict`) with --out/DIR there")
    if posterior.exists():
        tree = load(posterior)
        print(f"posterior ({tree.attrs.get('method', '?')}): {posterior}")
        _print_posterior(tree)
    if ens.exists():
        with xr.open_dataset(ens, engine="h5netcdf") as ds:
            print(f"ensemble: {ens}")
            _print_ensemble(ds.load())
    return 0


def demo(args) -> int:
    from bayespd.ensemble.demo_inputs import write_inputs

    out = Path(args.out or tempfile.mkdtemp(prefix="bayespd-demo-"))
    paths = write_inputs(out)
    print(f"demo inputs in {out}: model.py, scene.py, data.npz")
    run = out / "run"
    steps = [["calibrate", str(paths["model"]), "--data", str(paths["data"]), "--method", "laplace",
              "--out", str(run), "--samples", "200"],
             ["predict", str(run), "--scene", str(paths["scene"]), "--n", str(args.n), "--workers", str(args.workers)],
             ["summary", str(run)]]
    for step in steps:
        print("$ bayespd " + " ".join(step), flush=True)
        code = main(step + (["--quiet"] if args.quiet and step[0] != "summary" else []))
        if code:
            return code
    return 0


def _count(minimum: int):
    """An argparse type: an integer >= ``minimum``."""
    def count(text):
        try:
            value = int(text)
        except ValueError:
            value = None
        if value is None or value < minimum:
            raise argparse.ArgumentTypeError(f"must be an integer >= {minimum}, not {text!r}")
        return value
    count.__name__ = f"integer >= {minimum}"
    return count


def parser() -> argparse.ArgumentParser:
    top = argparse.ArgumentParser(prog="bayespd", description=__doc__.split("\n\n")[0],
                                  epilog=__doc__.split("\n\n", 2)[2], formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = top.add_subparsers(dest="command", required=True, metavar="COMMAND")
    c = sub.add_parser("calibrate", help="fit MODEL.py to DATA: writes DIR/posterior.nc",
                       description="Calibrate: MODEL.py defines scene() and model(scene) (tikhonov: init(), "
                                   "optionally fixed()); DATA.npz holds y (+ other keyword data).")
    c.add_argument("model", metavar="MODEL.py")
    c.add_argument("--data", required=True, metavar="DATA.npz", help="observations y (+ e.g. mask)")
    c.add_argument("--method", required=True, choices=METHODS)
    c.add_argument("--out", required=True, metavar="DIR", help="folder for posterior.nc")
    c.add_argument("--samples", type=_count(1), default=500, help="posterior draws (default 500)")
    c.add_argument("--warmup", type=_count(0), default=500, help="NUTS warm-up steps (default 500)")
    c.add_argument("--chains", type=_count(1), default=2, help="NUTS chains (default 2)")
    c.add_argument("--checkpoint", default=None, metavar="CKPT",
                   help="NUTS: save the chains in folder CKPT as they go; the same command resumes a killed run")
    c.add_argument("--checkpoint-every", type=_count(1), default=50, help="draws between checkpoint saves (default 50)")
    c.add_argument("--svi-steps", type=_count(1), default=2000, help="SVI optimisation steps (default 2000)")
    c.add_argument("--seed", type=int, default=0)
    p = sub.add_parser("predict", help="posterior-predictive crack ensemble from DIR/posterior.nc",
                       description="Run the crack ensemble of SCENE.py (fracture_scene() -> FractureScene) at "
                                   "draws of DIR/posterior.nc; writes DIR/ensemble/ and resumes a partial run.")
    p.add_argument("dir", metavar="DIR")
    p.add_argument("--scene", required=True, metavar="SCENE.py")
    p.add_argument("--n", type=int, default=200, help="posterior realisations (default 200)")
    p.add_argument("--n-mean", type=int, default=None, help="realisations at the posterior mean (default: n)")
    p.add_argument("--seed", type=int, default=0, help="ensemble seed: realisation i uses (seed, i)")
    p.add_argument("--workers", type=int, default=2, help="local worker processes (default 2; 1: in process)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS", help="a dask.distributed scheduler address")
    p.add_argument("--device", default=None, help="torch device of each realisation (default cpu)")
    s = sub.add_parser("summary", help="print the posterior and the ensemble of DIR")
    s.add_argument("dir", metavar="DIR")
    d = sub.add_parser("demo", help="write example inputs and run calibrate, predict, summary on them")
    d.add_argument("--out", default=None, metavar="DIR", help="folder (default: a new temporary one)")
    d.add_argument("--n", type=int, default=8, help="posterior realisations (default 8)")
    d.add_argument("--workers", type=int, default=2)
    for q in (c, p, d):
        q.add_argument("--quiet", action="store_true", help="no progress bars")
    return top


def main(argv=None) -> int:
    """Entry point; returns the exit code (0 done, 2 usage, 1 failure)."""
    args = parser().parse_args(argv)  # argparse exits with 2 on bad options
    command = {"calibrate": calibrate, "predict": predict, "summary": summary, "demo": demo}[args.command]
    try:
        return command(args)
    except UsageError as e:
        print(f"bayespd {args.command}: error: {e}", file=sys.stderr)
        return USAGE
    except (ValueError, RuntimeError, OSError) as e:
        print(f"bayespd {args.command}: failed: {type(e).__name__}: {e}", file=sys.stderr)
        return FAILURE


if __name__ == "__main__":
    sys.exit(main())
