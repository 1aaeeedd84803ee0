"""``glint remote ...`` (and ``glint-remote ...``): the client on the command line.

Human output by default (ids on stdout, chatter and bars on stderr), ``--json`` for
scripts. The exit code says how it went (docs/client.md lists them):
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from glint_client._version import __version__
from glint_client.client import Client
from glint_client.errors import (
    GlintAPIError,
    GlintClientError,
    IntegrityError,
    ServerError,
    ServerUnreachable,
)
from glint_client.models import Job, Scene
from glint_client.progress import ByteBar, TrainingBar, bars_enabled, duration, job_line

EXIT_OK = 0  # done; for commands that wait, the job succeeded
EXIT_JOB_FAILED = 1  # the job ended failed
EXIT_USAGE = 2  # bad arguments, no key, a local path that is missing or unreadable
EXIT_API = 3  # the API refused the request (4xx): its type and fields are printed
EXIT_SERVER = 4  # no answer from the server, a 5xx, or a download that failed its checksum
EXIT_CANCELLED = 5  # the job ended cancelled
EXIT_INTERRUPTED = 130  # Ctrl-C (the job itself goes on on the server)
EXIT_CODES = {
    EXIT_OK: "success (for commands that wait: the job succeeded)",
    EXIT_JOB_FAILED: "the job failed",
    EXIT_USAGE: "usage error: bad arguments, no API key, a missing or unreadable local path",
    EXIT_API: "the API refused the request (4xx): bad key, unknown id, invalid scene, ...",
    EXIT_SERVER: "server unreachable, a server error (5xx), or a download checksum mismatch",
    EXIT_CANCELLED: "the job was cancelled",
    EXIT_INTERRUPTED: "interrupted (Ctrl-C); a job keeps running on the server",
}
__doc__ = (__doc__ or "") + "\n" + "\n".join(f"    {c:>3}  {t}" for c, t in EXIT_CODES.items())
DEFAULT_SERVER = "http://127.0.0.1:8000"

Handler = Callable[[argparse.Namespace], int]


class UsageError(GlintClientError):
    """A problem with the command line itself (exit 2)."""


# --- output ------------------------------------------------------------------------------


def say(text: str) -> None:
    """Chatter for people: stderr, so stdout holds only what a script captures."""
    print(text, file=sys.stderr, flush=True)


def emit(args: argparse.Namespace, human: str, data: Any) -> None:
    """The command's result: ``data`` as JSON with --json, else the ``human`` text."""
    if args.json:
        print(json.dumps(data, indent=None if isinstance(data, list) else 2, default=str))
    elif human:
        print(human)


def _size(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB"):
        if abs(n) < 1024 or unit == "GiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} GiB"


def _job_exit(job: Job) -> int:
    return {"failed": EXIT_JOB_FAILED, "cancelled": EXIT_CANCELLED}.get(job["state"], EXIT_OK)


def _job_summary(job: Job) -> str:
    text = f"job {job['id']} {job['state']}"
    if job.get("kind") == "mesh":  # its progress is the mesh stage, not iterations
        return text + (f": {job['error']}" if job.get("error") else "")
    if job["state"] == "succeeded":
        m = job.get("metrics") or {}
        bits = [f"{job.get('iteration')} iterations in {duration(job.get('elapsed_s'))}"]
        if m.get("psnr") is not None:
            bits.append(f"PSNR {m['psnr']:.2f} dB")
        text += ": " + ", ".join(bits)
    elif job.get("error"):
        text += f": {job['error']}"
    return text


# --- client and options ------------------------------------------------------------------


def _client(args: argparse.Namespace) -> Client:
    server = getattr(args, "server", None) or os.environ.get("GLINT_SERVER") or DEFAULT_SERVER
    key = getattr(args, "key", None) or os.environ.get("GLINT_KEY")
    if not key:
        raise UsageError(
            "no API key: pass --key or set GLINT_KEY (on the server, `glint keys create NAME` "
            "prints one)"
        )
    retries = getattr(args, "retries", None)
    return Client(server, key, retries=4 if retries is None else retries)


def _value(text: str) -> Any:
    """A ``--set`` value: JSON when it parses (numbers, true, lists), else the string."""
    try:
        return json.loads(text)
    except ValueError:
        return text


def _config(args: argparse.Namespace) -> dict[str, Any]:
    config: dict[str, Any] = {}
    if args.config:
        try:
            loaded = json.loads(Path(args.config).read_text())
        except (OSError, ValueError) as exc:
            raise UsageError(f"--config {args.config}: not a readable JSON file ({exc})") from exc
        if not isinstance(loaded, dict):
            raise UsageError(f"--config {args.config}: expected a JSON object")
        config.update(loaded)
    for item in args.set or []:
        name, eq, raw = item.partition("=")
        if not eq or not name.strip():
            raise UsageError(f"--set expects KEY=VALUE (dotted keys for sections), got '{item}'")
        node = config
        *parents, leaf = name.strip().split(".")
        for p in parents:
            child = node.setdefault(p, {})
            if not isinstance(child, dict):
                raise UsageError(f"--set {item}: '{p}' is not a section")
            node = child
        node[leaf] = _value(raw)
    return config


def _pairs(items: Sequence[str] | None, option: str) -> dict[str, Any] | None:
    if not items:
        return None
    out = {}
    for item in items:
        name, eq, raw = item.partition("=")
        if not eq:
            raise UsageError(f"{option} expects KEY=VALUE, got '{item}'")
        out[name.strip()] = _value(raw)
    return out


# --- commands ----------------------------------------------------------------------------


def _follow(client: Client, args: argparse.Namespace, job_id: str) -> Job:
    """Follow a job to its end with a training bar; returns its final state."""
    bar = TrainingBar(enabled=bars_enabled(args.quiet), quiet=args.quiet or args.json)
    job: Job | None = None
    try:
        for job in client.follow(job_id):
            bar.update(job)
    finally:
        bar.close()
    if job is None or job["state"] not in ("succeeded", "failed", "cancelled"):
        job = client.get_job(job_id)
    return job


def _download(client: Client, args: argparse.Namespace, job_id: str, dest: str) -> list[Path]:
    only = getattr(args, "only", None)
    with ByteBar("download", enabled=bars_enabled(args.quiet)) as bar:
        paths = client.download(
            job_id,
            dest,
            only,
            parallel=args.parallel,
            on_bytes=bar.update,
            on_artifacts=lambda arts: bar.set_total(sum(a["size"] for a in arts)),
        )
    if not args.quiet:
        say(f"downloaded {len(paths)} files ({_size(bar.done)}) into {dest}, checksums verified")
    return paths


def _scene_report(scene: Scene) -> str:
    r = scene.get("report") or {}
    text = f"scene {scene['id']} {scene['state']}"
    if r:
        text += (
            f": {r.get('format')}, {r.get('views')} views ({r.get('train_views')} train, "
            f"{r.get('test_views')} test)"
        )
        if r.get("resolution"):
            text += f", {r['resolution'][0]}x{r['resolution'][1]}"
        if r.get("needs_sfm"):
            text += "; photos without poses: the job starts with structure from motion"
        for w in r.get("warnings") or []:
            text += f"\n  warning: {w}"
    return text


def cmd_submit(args: argparse.Namespace) -> int:
    config = _config(args)
    sfm = _pairs(args.sfm, "--sfm")
    sources = [Path(p) for p in args.path]
    for s in sources:
        if not s.exists():
            raise UsageError(f"{s}: no such file or folder")
    with _client(args) as client:

        def announce(scene: Scene) -> None:
            if not args.quiet:
                say(
                    f"scene {scene['id']} ({scene['name']}); if the upload is interrupted, "
                    f"run the same command with --scene {scene['id']} to continue it"
                )

        with ByteBar("upload", enabled=bars_enabled(args.quiet)) as bar:
            scene = client.create_scene_from(
                sources,
                name=args.name,
                scene_id=args.scene,
                parallel=args.parallel,
                on_bytes=bar.update,
                on_files=lambda files: bar.set_total(sum(f.size for f in files)),
                on_scene=announce,
            )
        if not args.quiet:
            say(_scene_report(scene))
        hook = {"url": args.webhook} if args.webhook else None
        try:
            job = client.create_job(
                scene["id"],
                config,
                iterations=args.iterations,
                time_budget=args.time,
                sfm=sfm,
                webhook=hook,
            )
        except GlintAPIError:  # the upload is done: say how to reuse it
            say(
                f"the scene {scene['id']} is uploaded and {scene['state']}; after fixing the "
                f"job's options, add --scene {scene['id']} to send nothing again"
            )
            raise
        secret = (job.get("webhook") or {}).get("secret")
        if secret and not args.json:
            say(f"webhook secret (keep it; it is not shown again): {secret}")
        return _started(client, args, job)


def _started(client: Client, args: argparse.Namespace, job: Job) -> int:
    """A job was just created: print its id, and follow and download it when asked."""
    if not args.json:
        print(job["id"], flush=True)
    if not (args.wait or args.download):
        if args.json:
            emit(args, "", job)
        return EXIT_OK
    job = _follow(client, args, job["id"])
    if not args.quiet:
        say(_job_summary(job))
    if args.download and job["state"] == "succeeded":
        _download(client, args, job["id"], args.download)
    if args.json:
        emit(args, "", job)
    return _job_exit(job)


def cmd_status(args: argparse.Namespace) -> int:
    with _client(args) as client:
        job = client.get_job(args.job)
    human = job_line(job)
    if job.get("error"):
        human += f"\n  error: {job['error']}"
    emit(args, human, job)
    return EXIT_OK


def cmd_follow(args: argparse.Namespace) -> int:
    with _client(args) as client:
        job = _follow(client, args, args.job)
    emit(args, _job_summary(job), job)
    return _job_exit(job)


def cmd_list(args: argparse.Namespace) -> int:
    with _client(args) as client:
        if args.scenes:
            scenes = list(client.list_scenes(args.state[0] if args.state else None))
            lines = [
                f"{s['id']}  {s['state']:<10} {s.get('format') or '-':<9} "
                f"{s['file_count']:>5} files  {_size(s['total_bytes']):>10}  {s['name']}"
                for s in scenes
            ]
            emit(args, "\n".join(lines), scenes)
            return EXIT_OK
        jobs = list(client.list_jobs(args.state, scene_id=args.scene_id, kind=args.kind))
    lines = []
    for j in jobs:
        psnr = (j.get("metrics") or {}).get("psnr")
        lines.append(
            f"{j['id']}  {j['state']:<9} {j.get('kind', 'train'):<5} "
            f"{j.get('iteration', 0):>7}/{j.get('total_iterations', 0):<7} "
            f"{'-' if psnr is None else f'{psnr:.2f} dB':>9}  {j['scene_id']}  {j['created_at']}"
        )
    emit(args, "\n".join(lines), jobs)
    return EXIT_OK


def cmd_download(args: argparse.Namespace) -> int:
    with _client(args) as client:
        if args.list:
            arts = client.artifacts(args.job)
            lines = [f"{_size(a['size']):>10}  {a['sha256'][:12]}  {a['name']}" for a in arts]
            emit(args, "\n".join(lines), arts)
            return EXIT_OK
        paths = _download(client, args, args.job, args.dest or args.job)
    emit(args, "\n".join(str(p) for p in paths), [str(p) for p in paths])
    return EXIT_OK


def cmd_cancel(args: argparse.Namespace) -> int:
    with _client(args) as client:
        job = client.cancel(args.job)
    human = f"job {job['id']} {job['state']}"
    if job.get("cancel_requested") and job["state"] == "running":
        human += " (cancel requested: it stops at its next check, after a checkpoint)"
    emit(args, human, job)
    return EXIT_OK


def cmd_delete(args: argparse.Namespace) -> int:
    with _client(args) as client:
        client.delete_job(args.job)
    emit(args, f"job {args.job} deleted", {"id": args.job, "deleted": True})
    return EXIT_OK


def cmd_metrics(args: argparse.Namespace) -> int:
    with _client(args) as client:
        rows = client.metrics(args.job, points=args.points)
    lines = [f"{'iteration':>9} {'time':>8} {'PSNR':>7} {'SSIM':>6} phase"]
    for r in rows:
        psnr, ssim = r.get("psnr"), r.get("ssim")
        lines.append(
            f"{r['iteration']:>9} {duration(r.get('wall_time')):>8} "
            f"{'-' if psnr is None else f'{psnr:.2f}':>7} "
            f"{'-' if ssim is None else f'{ssim:.3f}':>6} {r.get('phase', '')}"
        )
    emit(args, "\n".join(lines), rows)
    return EXIT_OK


def cmd_mesh(args: argparse.Namespace) -> int:
    params = {
        k: v
        for k, v in {
            "resolution": args.resolution,
            "voxel": args.voxel,
            "color": args.color,
            "simplify": args.simplify,
            "grazing_blend": args.grazing_blend,
        }.items()
        if v is not None
    }
    with _client(args) as client:
        return _started(client, args, client.create_mesh(args.job, **params))


# --- errors to exit codes ----------------------------------------------------------------


def _report_api_error(prog: str, exc: GlintAPIError) -> None:
    print(f"{prog}: {exc}", file=sys.stderr)
    if exc.status == 401:
        print("  (check --key / GLINT_KEY: the key is unknown or revoked)", file=sys.stderr)
    elif exc.status == 403:
        print("  (this key's scope does not allow it: use a 'write' key)", file=sys.stderr)


def run(handler: Handler, args: argparse.Namespace, prog: str = "glint remote") -> int:
    """Run a command, turning every expected failure into its message and exit code."""
    try:
        return handler(args)
    except UsageError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except ServerError as exc:
        _report_api_error(prog, exc)
        return EXIT_SERVER
    except GlintAPIError as exc:
        _report_api_error(prog, exc)
        return EXIT_API
    except (ServerUnreachable, IntegrityError) as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return EXIT_SERVER
    except GlintClientError as exc:  # local: unreadable archive, missing file, ...
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print(f"{prog}: interrupted (a job already started keeps running)", file=sys.stderr)
        return EXIT_INTERRUPTED


# --- parser ------------------------------------------------------------------------------


def _common(suppress: bool) -> argparse.ArgumentParser:
    """Options every command takes, before or after its name (``suppress``: a later
    parser leaves what an earlier one set alone)."""
    d: dict[str, Any] = {"default": argparse.SUPPRESS} if suppress else {}
    p = argparse.ArgumentParser(add_help=False)
    g = p.add_argument_group("connection and output")
    g.add_argument("--server", help=f"API server URL (env GLINT_SERVER; {DEFAULT_SERVER})", **d)
    g.add_argument("--key", help="API key (env GLINT_KEY)", **d)
    g.add_argument(
        "--retries",
        type=int,
        help="retries of a call that may be repeated, after a connection failure or a "
        "502/503/504 (default 4)",
        **d,
    )
    g.add_argument("--json", action="store_true", help="print JSON for scripts", **d)
    g.add_argument("--quiet", "-q", action="store_true", help="no progress bars or chatter", **d)
    return p


def _wait_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--wait", action="store_true", help="follow the job to its end")
    p.add_argument(
        "--download",
        metavar="DIR",
        help="when it succeeds, download its artifacts (implies --wait)",
    )
    p.add_argument("--parallel", type=int, default=4, help="files sent or fetched at once (4)")


def add_commands(parser: argparse.ArgumentParser, prog: str) -> None:
    """The remote commands as sub-commands of ``parser``."""
    common = _common(suppress=True)
    sub = parser.add_subparsers(dest="remote_command", metavar="COMMAND")

    def command(name: str, handler: Handler, help_text: str, **kw: Any) -> argparse.ArgumentParser:
        p = sub.add_parser(name, help=help_text, description=help_text, parents=[common], **kw)
        p.set_defaults(func=lambda a: run(handler, a, prog))
        return p

    p = command(
        "submit",
        cmd_submit,
        "upload a capture (a scene folder, a zip/tar archive, or photos without poses), "
        "commit it and start a training job; prints the job id",
    )
    p.add_argument("path", nargs="+", help="scene folder, archive, or photo files")
    p.add_argument("--name", help="scene name (default: the folder's or archive's name)")
    p.add_argument(
        "--scene", metavar="SCENE_ID", help="continue uploading into this open scene (resume)"
    )
    p.add_argument("--time", metavar="DURATION", help="time budget: 90s, 5m, 1h30m")
    p.add_argument("--iterations", type=int, help="training iterations")
    p.add_argument("--config", metavar="FILE", help="training config as a JSON file")
    p.add_argument(
        "--set", action="append", metavar="KEY=VALUE", help="config field, e.g. loss.scale=50"
    )
    p.add_argument(
        "--webhook", metavar="URL", help="POST the job's end to this URL (signed; secret printed)"
    )
    p.add_argument(
        "--sfm",
        action="append",
        metavar="KEY=VALUE",
        help="SfM option for photos, e.g. matching=exhaustive",
    )
    _wait_options(p)

    p = command("status", cmd_status, "a job's state, phase, iteration, PSNR and time left")
    p.add_argument("job")
    p = command("follow", cmd_follow, "follow a job to its end (exit code: how it ended)")
    p.add_argument("job")
    p = command("list", cmd_list, "list jobs (newest first), or scenes with --scenes")
    p.add_argument("--state", action="append", help="only these states (repeatable)")
    p.add_argument("--scene-id", help="only jobs of this scene")
    p.add_argument("--kind", choices=("train", "mesh"), help="only training or mesh jobs")
    p.add_argument("--scenes", action="store_true", help="list scenes instead of jobs")
    p = command(
        "download",
        cmd_download,
        "download a job's artifacts (parallel, resumable, SHA-256 verified)",
    )
    p.add_argument("job")
    p.add_argument("dest", nargs="?", help="folder (default: the job id)")
    p.add_argument(
        "--only", action="append", metavar="NAME", help="artifact name or glob (repeatable)"
    )
    p.add_argument("--list", action="store_true", help="list the artifacts, download nothing")
    p.add_argument("--parallel", type=int, default=4, help="files fetched at once (4)")
    p = command("cancel", cmd_cancel, "cancel a job")
    p.add_argument("job")
    p = command("delete", cmd_delete, "delete a finished job and its files")
    p.add_argument("job")
    p = command("metrics", cmd_metrics, "a job's error against training time")
    p.add_argument("job")
    p.add_argument("--points", type=int, help="thin the series to this many rows")
    p = command("mesh", cmd_mesh, "extract another mesh from a succeeded training job")
    p.add_argument("job")
    p.add_argument("--resolution", type=int, help="voxels along the longest side (256)")
    p.add_argument("--voxel", type=float, help="voxel size in scene units (instead)")
    p.add_argument("--color", choices=("base", "radiance"), help="vertex colour (base)")
    p.add_argument("--simplify", type=int, help="decimate to about this many faces")
    p.add_argument(
        "--grazing-blend",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="centre depth where the surface is seen obliquely (the server's default: on)",
    )
    _wait_options(p)


def _epilog() -> str:
    return "exit codes:\n" + "\n".join(f"  {c:>3}  {t}" for c, t in EXIT_CODES.items())


def _no_command(parser: argparse.ArgumentParser) -> Handler:
    def show(args: argparse.Namespace) -> int:
        parser.print_help(sys.stderr)
        return EXIT_USAGE

    return show


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """``glint remote ...``: added to the main ``glint`` command by its entry point."""
    p = sub.add_parser(
        "remote",
        help="talk to a Glint server: submit captures, follow jobs, download results",
        description="Talk to a Glint server over its REST API (docs/client.md).",
        epilog=_epilog(),
        formatter_class=argparse.RawDescriptionHelpFormatter,
        parents=[_common(suppress=False)],
    )
    add_commands(p, "glint remote")
    p.set_defaults(func=_no_command(p))


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="glint-remote",
        description="Talk to a Glint server over its REST API (docs/client.md).",
        epilog=_epilog(),
        formatter_class=argparse.RawDescriptionHelpFormatter,
        parents=[_common(suppress=False)],
    )
    parser.add_argument("--version", action="version", version=f"glint-client {__version__}")
    add_commands(parser, "glint-remote")
    parser.set_defaults(func=_no_command(parser))
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """``glint-remote``: the same commands without the server's ``glint`` installed."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args))
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
