"""Command line of the surrogate: ``surrogate train | evaluate | predict``.

    surrogate train DATASET.h5 --out MODEL.pt [--ensemble N] [--epochs E] [--seed S]
    surrogate evaluate MODEL.pt DATASET.h5 [--out-dir DIR] [--folds K --repeats R]
    surrogate predict MODEL.pt --params d0=9e-6 phi=2.5 [--json]

Exit codes: 0 done; 2 bad input (unknown or out-of-range parameter, unusable dataset or model
file: the message names the key, the value and the allowed range); 1 anything else.
Progress bars go to stderr (``--quiet`` turns them off).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from calendaring import (
    EXIT_OK,
    ConfigError,
    ContractParser,
    DatasetError,
    output_path,
    run_cli,
)
from surrogate.checkpoint import CheckpointError, json_default


def _set_threads(n: int | None) -> None:
    import torch

    if n is not None:
        if n < 1:
            raise ConfigError("--threads", n, "an integer >= 1")
        torch.set_num_threads(int(n))


def cmd_train(args) -> int:
    from calendaring import read_dataset
    from surrogate.api import SurrogateModel
    from surrogate.ensemble import train_ensemble
    from surrogate.evaluate import loss_table_markdown, model_metrics, summary_lines
    from surrogate.model import ModelConfig
    from surrogate.train import TrainConfig

    out = output_path(args.out, "--out", overwrite=args.overwrite)
    if args.ensemble < 1:
        raise ConfigError("--ensemble", args.ensemble, "an integer >= 1")
    _set_threads(args.threads)
    ds = read_dataset(args.dataset)
    roles = ("train", "replicate") if args.include_replicates else ("train",)
    cfg = TrainConfig(epochs=args.epochs, batch_size=args.batch_size, lr=args.lr,
                      weight_decay=args.weight_decay, patience=args.patience, seed=args.seed,
                      mse_weight=args.mse_weight, kl_weight=args.kl_weight, train_roles=roles,
                      pressure_head=args.pressure_head, gp_components=args.gp_components)
    model_config = ModelConfig(dropout=args.dropout)
    t0 = time.perf_counter()
    results = train_ensemble(ds, args.ensemble, cfg, model_config, progress=not args.quiet)
    seconds = time.perf_counter() - t0
    model = SurrogateModel.from_training(results, ds, {"train_seconds_total": seconds,
                                                       "command": "surrogate train " +
                                                       " ".join(args.argv)})
    test = results[0].rows["test"]
    model.info["metrics"] = {"test": model_metrics(model, ds, test)}
    model.save(out)
    kind = f"ensemble of {args.ensemble}" if args.ensemble > 1 else "single model"
    print(f"wrote {out}: {kind}, {len(results[0].rows['train'])} training / "
          f"{len(results[0].rows['val'])} validation / {len(test)} test runs "
          f"(roles {list(roles)}), {seconds:.1f} s")
    for k, r in enumerate(results):
        stop = " (early stop)" if r.history.stopped_early else ""
        print(f"member {k}: best epoch {r.history.best_epoch} of {len(r.history.train_total)}"
              f"{stop}")
    gp = model.info.get("pressure_gp")
    if gp:
        print(f"pressure from PCA + GP: {gp['n_components']} components "
              f"({100 * sum(gp['explained_variance_ratio']):.3g} % of the curves' variance) "
              f"fitted on {gp['n_rows']} runs in {gp['fit_seconds']:.1f} s; the network's "
              "pressure head is trained but not used")
    print(loss_table_markdown(results[0].loss_table, "Loss per branch (member 0)"), end="")
    for line in summary_lines({"metrics": model.info["metrics"]}):
        print(line)
    return EXIT_OK


def cmd_evaluate(args) -> int:
    from calendaring import read_dataset
    from surrogate.api import load
    from surrogate.evaluate import evaluate, summary_lines

    _set_threads(args.threads)
    if args.folds and args.folds < 2:
        raise ConfigError("--folds", args.folds, "0 (off) or an integer >= 2")
    model = load(args.model)
    ds = read_dataset(args.dataset)
    out_dir = Path(args.out_dir) if args.out_dir else \
        Path(args.model).with_name(Path(args.model).stem + "_eval")
    output_path(out_dir, "--out-dir", folder=True)
    res = evaluate(model, ds, out_dir, folds=args.folds, repeats=args.repeats,
                   epochs=args.epochs, baseline=not args.no_baseline,
                   progress=not args.quiet)
    if not res["same_dataset_as_training"]:
        print("note: the dataset is not the one the model was trained on (fingerprint "
              "differs); every 'train' row is evaluated")
    for line in summary_lines(res):
        print(line)
    print(f"wrote {', '.join(res['files'])} to {out_dir}")
    return EXIT_OK


def cmd_learning_curve(args) -> int:
    from calendaring import read_dataset
    from surrogate.learning import format_learning_curve, learning_curve
    from surrogate.train import TrainConfig, config_for

    _set_threads(args.threads)
    ds = read_dataset(args.dataset)
    out_dir = output_path(args.out_dir, "--out-dir", folder=True)
    cfg = TrainConfig(epochs=args.epochs, batch_size=args.batch_size, lr=args.lr,
                      patience=args.patience, seed=args.seed, mse_weight=args.mse_weight,
                      kl_weight=args.kl_weight, pressure_head=args.pressure_head,
                      gp_components=args.gp_components)
    model_config = config_for(ds, dropout=args.dropout)
    res = learning_curve(ds, args.sizes, args.repeats, cfg, model_config, out_dir,
                         target=args.target, progress=not args.quiet)
    for line in format_learning_curve(res):
        print(line)
    print(f"wrote {', '.join(res.get('files', []))} to {out_dir}")
    return EXIT_OK


def parse_params(items: list[str]) -> dict[str, list[float]]:
    """``["d0=9e-6", "phi=1,2"]`` -> ``{"d0": [9e-6], "phi": [1.0, 2.0]}``."""
    out = {}
    for item in items or []:
        if "=" not in item:
            raise ConfigError("--params", item, "name=value (or name=v1,v2,...)")
        key, _, val = item.partition("=")
        key = key.strip()
        try:
            out[key] = [float(v) for v in val.split(",")]
        except ValueError:
            raise ConfigError(key, val, "a number or comma-separated numbers") from None
    return out


def cmd_predict(args) -> int:
    from calendaring import centroids
    from surrogate.api import load
    from surrogate.evaluate import STROKE_FRACTIONS, stroke_index

    model = load(args.model)
    params = parse_params(args.params)
    pred = model.predict(params)
    cents = centroids(pred.distribution, model.load_centres, model.diameter_centres,
                      model.load_scale == "log")
    if args.json:
        rows = []
        for k in range(len(pred)):
            rows.append({
                "params": model.space.as_dict(pred.params[k]),
                "pressure_Pa": pred.pressure[k],
                "pressure_std_Pa": None if pred.pressure_std is None else pred.pressure_std[k],
                "distribution": pred.distribution[k],
                "distribution_std": None if pred.distribution_std is None
                else pred.distribution_std[k],
                "centroid_load_N": cents[k, 0], "centroid_diameter_m": cents[k, 1]})
        print(json.dumps({"model": str(args.model), "is_ensemble": model.is_ensemble,
                          "defaulted_to_reference": pred.defaulted,
                          "units": {"params": dict(zip(model.space.names, model.space.units,
                                                       strict=True)),
                                    "depth": "m", "pressure": "Pa", "distribution":
                                    "probability per [load bin, diameter bin]"},
                          "depth_m": model.depth, "load_edges_N": model.load_edges,
                          "diameter_edges_m": model.diameter_edges, "predictions": rows},
                         default=json_default))
        return EXIT_OK
    if pred.defaulted:
        print("note: not given, set to the reference values: " + ", ".join(
            f"{n}={model.space[n].reference:g}" for n in pred.defaulted))
    kind = f"ensemble of {model.n_members} (mean +- std)" if model.is_ensemble else "single model"
    print(f"{model.info.get('path', args.model)}: {kind}")
    for k in range(len(pred)):
        given = ", ".join(f"{n}={pred.params[k, i]:g}" for i, n in enumerate(model.space.names))
        print(f"[{k}] {given}")
        parts = []
        for f in STROKE_FRACTIONS:
            j = stroke_index(len(model.depth), f)
            s = f"{model.depth[j] * 1e6:.2f} um: {pred.pressure[k, j] / 1e6:.4g}"
            if pred.pressure_std is not None:
                s += f" +- {pred.pressure_std[k, j] / 1e6:.2g}"
            parts.append(s + " MPa")
        print("    pressure at " + "; ".join(parts))
        print(f"    breakage centroid: peak load {cents[k, 0]:.4g} N, parent diameter "
              f"{cents[k, 1] * 1e6:.3g} um")
    return EXIT_OK


def heads(p: argparse.ArgumentParser) -> None:
    p.add_argument("--pressure-head", choices=("mlp", "gp"), default="mlp",
                   help="where predictions take the pressure from: the network's head (the "
                        "paper's) or a PCA + GP branch fitted on the same training rows "
                        "(default mlp)")
    p.add_argument("--gp-components", type=int, default=8,
                   help="principal components of the GP branch (default 8)")


def build_parser() -> argparse.ArgumentParser:
    p = ContractParser(prog="surrogate", description="Dual-branch MLP surrogate of "
                       "the calendering pressure curve and breakage distribution.")
    sub = p.add_subparsers(dest="command", required=True, parser_class=ContractParser)

    t = sub.add_parser("train", help="train a model or deep ensemble on a dataset file")
    t.add_argument("dataset", help="dataset file (calendaring dataset ... --out DATASET.h5)")
    t.add_argument("--out", required=True, help="checkpoint to write (MODEL.pt)")
    t.add_argument("--ensemble", type=int, default=1, help="members (deep ensemble; 5 is a "
                   "good choice; default 1, a single model)")
    t.add_argument("--epochs", type=int, default=80, help="epochs (default 80, as the paper)")
    t.add_argument("--seed", type=int, default=0, help="seed of the split, weights, batches")
    t.add_argument("--batch-size", type=int, default=16)
    t.add_argument("--lr", type=float, default=1e-3, help="Adam learning rate")
    t.add_argument("--weight-decay", type=float, default=1e-5, help="Adam weight decay")
    t.add_argument("--patience", type=int, default=20,
                   help="early stopping after this many epochs without a lower validation "
                        "loss (0: off; the best weights are kept either way)")
    t.add_argument("--mse-weight", type=float, default=0.7,
                   help="weight of the pressure MSE in the loss (default 0.7, as the paper)")
    t.add_argument("--kl-weight", type=float, default=0.3,
                   help="weight of the distribution KL in the loss (default 0.3, as the paper)")
    t.add_argument("--dropout", type=float, default=0.3,
                   help="dropout probability throughout the network (default 0.3, as the "
                        "paper)")
    heads(t)
    t.add_argument("--include-replicates", action="store_true",
                   help="also split and train on 'replicate' rows (default: 'train' rows "
                        "only; 'holdout' rows are never used)")
    t.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    t.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    t.add_argument("--quiet", action="store_true", help="no progress bar")
    t.set_defaults(func=cmd_train)

    e = sub.add_parser("evaluate", help="metrics, Table 3, Fig. 5 and CV of a model")
    e.add_argument("model", help="checkpoint (MODEL.pt)")
    e.add_argument("dataset", help="dataset file with the model's depths and bins")
    e.add_argument("--out-dir", help="output folder (default: MODEL_eval next to the model)")
    e.add_argument("--folds", type=int, default=0, help="K of repeated K-fold CV (0: off)")
    e.add_argument("--repeats", type=int, default=1, help="repeats of the K-fold CV")
    e.add_argument("--epochs", type=int, default=None,
                   help="epochs per CV fit (default: the checkpoint's)")
    e.add_argument("--no-baseline", action="store_true", help="skip the PCA + GP baseline")
    e.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    e.add_argument("--quiet", action="store_true", help="no progress bar")
    e.set_defaults(func=cmd_evaluate)

    c = sub.add_parser("learning-curve", help="error on the held-out seed means against "
                       "the number of training runs, and the runs a target takes")
    c.add_argument("dataset", help="dataset file with holdout groups of >= 2 seeds")
    c.add_argument("--out-dir", required=True, help="output folder (resumed when it holds "
                   "a learning curve of the same dataset and settings)")
    c.add_argument("--sizes", type=int, nargs="+",
                   help="training-run counts (default: the trainable rows and up to 3 "
                        "halvings of them)")
    c.add_argument("--repeats", type=int, default=3, help="shuffles of the training rows "
                   "(the spread of each point; default 3)")
    c.add_argument("--target", type=float, default=3e-4,
                   help="pressure MSE target, normalised units (default 3e-4, the paper's)")
    c.add_argument("--epochs", type=int, default=80)
    c.add_argument("--batch-size", type=int, default=16)
    c.add_argument("--lr", type=float, default=1e-3)
    c.add_argument("--patience", type=int, default=20)
    c.add_argument("--dropout", type=float, default=0.3)
    c.add_argument("--mse-weight", type=float, default=0.7)
    c.add_argument("--kl-weight", type=float, default=0.3)
    heads(c)
    c.add_argument("--seed", type=int, default=0, help="seed of the shuffles and weights")
    c.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    c.add_argument("--quiet", action="store_true", help="no progress bar")
    c.set_defaults(func=cmd_learning_curve)

    r = sub.add_parser("predict", help="predict pressure and breakage distribution")
    r.add_argument("model", help="checkpoint (MODEL.pt)")
    r.add_argument("--params", nargs="*", default=[], metavar="NAME=VALUE",
                   help="physical values (SI; percent for alpha_percentage and "
                        "truncation_ratio); several sets as NAME=v1,v2; names not given "
                        "take the reference values")
    r.add_argument("--json", action="store_true", help="full curves and maps as JSON (SI)")
    r.set_defaults(func=cmd_predict)
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``surrogate`` command.

    Exit codes: :mod:`calendaring.core.cli_contract`.
    """
    from calendaring import __version__

    argv = list(sys.argv[1:] if argv is None else argv)

    def handle() -> int:
        args = build_parser().parse_args(argv)
        args.argv = argv
        return args.func(args)

    return run_cli("surrogate", handle, (DatasetError, CheckpointError), __version__)


if __name__ == "__main__":
    sys.exit(main())
