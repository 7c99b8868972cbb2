"""``python -m eval.bench_pipeline`` (the command from before the move) runs ``eval.bench.pipeline``."""

from eval.bench.pipeline import main

if __name__ == "__main__":
    raise SystemExit(main())
