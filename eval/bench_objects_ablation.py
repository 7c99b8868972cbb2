"""``python -m eval.bench_objects_ablation`` (issue 43's command) runs ``eval.bench.objects_ablation``."""

from eval.bench.objects_ablation import main

if __name__ == "__main__":
    raise SystemExit(main())
