"""``dualscale view RUN|OUT``: serve the web viewer of an exported material on localhost."""

from __future__ import annotations

import argparse
import sys

from dualscale.errors import EXIT_CODES, InputError, StopRequest, ToolError


def cmd_view(args: argparse.Namespace) -> int:
    from dualscale.view import ViewerServer, locate, vendor_missing
    from dualscale.view.server import VENDOR_HINT

    scene = locate(args.path)
    missing = vendor_missing()
    if missing:
        raise ToolError(f"the viewer's three.js files are missing ({', '.join(missing)}); {VENDOR_HINT}")
    if args.led is not None:
        ids = [d["id"] for d in scene.leds]
        if scene.no_capture is not None:
            raise InputError(f"--led {args.led}: no side-by-side for {args.path} ({scene.no_capture})")
        if args.led not in ids:
            raise InputError(f"--led {args.led}: the dataset {scene.dataset} has LEDs {ids[0]}..{ids[-1]}")
    try:
        server = ViewerServer(scene, port=args.port)
    except OSError as e:
        import errno

        if e.errno == errno.EADDRINUSE:
            raise InputError(f"--port {args.port}: the port is in use on 127.0.0.1; choose another, or 0 for any "
                             "free port") from e
        raise
    url = server.url + (f"?led={args.led}" if args.led is not None else "")
    try:
        print(f"dualscale view: serving {scene.root} at {url} (Ctrl-C to stop)", flush=True)
        if not args.no_browser:
            import webbrowser

            webbrowser.open(url)
        server.serve_forever()
    except StopRequest:  # SIGTERM, SIGHUP: the cache is removed below; main prints the one line
        args.resume_hint = "run the same command again to serve it again"
        raise
    except KeyboardInterrupt:
        print("", file=sys.stderr)
        return EXIT_CODES["interrupted"]
    finally:
        server.close()
    return 0


def _port(text: str) -> int:
    """argparse type of ``--port``: a TCP port 0..65535 (0 = any free port); a usage error
    otherwise (exit 2, one line), not an OverflowError from the socket."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"a TCP port 0..65535 (0 = any free port), got {text!r}") from None
    if not 0 <= n <= 65535:
        raise argparse.ArgumentTypeError(f"a TCP port is 0..65535 (0 = any free port), got {n}")
    return n


def register(subparsers) -> None:
    """Add ``view`` to an argparse subparsers object."""
    v = subparsers.add_parser(
        "view", help="show an exported material in a web viewer on localhost",
        description="Serve the web viewer (three.js, no network access) of a digitize RUN folder or an export "
                    "folder OUT on 127.0.0.1 and open it in the browser: the glTF on its swatch, a draped cloth "
                    "or a sphere, a movable light, the maps in false colour and, for a run, each LED's captured "
                    "image beside our renderer's image of the fitted maps (docs/VIEWER.md). Ctrl-C (or SIGTERM, SIGHUP) stops it.")
    v.add_argument("path", metavar="RUN|OUT", help="digitize run folder (run.json) or export folder (export.json) "
                                                  "with a glb or gltf export")
    v.add_argument("--port", type=_port, default=0, help="port on 127.0.0.1 (default: any free port)")
    v.add_argument("--no-browser", action="store_true", help="do not open a browser; just print the URL")
    v.add_argument("--led", type=int, default=None, metavar="K",
                   help="LED whose captured and rendered images the page shows first (a run only)")
    v.set_defaults(fn=cmd_view)
