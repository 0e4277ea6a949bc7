"""``fpmcal store dump`` and ``restore``: the store backed up or migrated (:mod:`store.backup`)."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from .inputs import ServiceError, SpecFileError, _one_line


def _store_redis() -> Any:
    import os

    from redis import Redis

    url = os.environ.get("FPM_REDIS_URL") or os.environ.get("REDIS_URL")
    return Redis.from_url(url or "redis://localhost:6379/0", socket_timeout=10)


def cmd_store(args: argparse.Namespace) -> None:
    from redis.exceptions import RedisError

    from store.backup import DumpError, dump, restore

    try:
        redis = _store_redis()
        if args.store_command == "dump":
            count = 0
            with open(args.output, "w", encoding="utf-8") as out:
                for line in dump(redis):
                    out.write(line + "\n")
                    count += 1
            print(f"wrote {args.output}: {count - 1} records", file=sys.stderr)
            return
        try:
            with open(args.file, encoding="utf-8") as lines:
                written = restore(redis, (line.rstrip("\n") for line in lines))
        except OSError as e:
            raise SpecFileError(f"{args.file}: {_one_line(e)}") from None
        except DumpError as e:
            raise ValueError(f"{args.file}: {e}") from None
        summary = ", ".join(f"{n} {kind.replace('_', ' ')}s" for kind, n in written.items())
        print(
            f"restored from {args.file}: {summary} (records already stored kept)", file=sys.stderr
        )
    except RedisError as e:
        raise ServiceError(f"Redis: {_one_line(e)}") from None
