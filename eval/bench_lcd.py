"""``python -m eval.bench_lcd`` (the command from before the move) runs ``eval.bench.lcd``."""

from eval.bench.lcd import main

if __name__ == "__main__":
    raise SystemExit(main())
