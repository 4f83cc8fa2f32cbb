"""`imubench station`: the calibration station page, idle (the person chooses the device,
method and options on the page); and the web face of `imubench calibrate --ui web`."""
from __future__ import annotations

import sys
from pathlib import Path

from imubench.cli.common import CommandError, add_sim, out_dir


def _http_port(s: str) -> int:
    import argparse
    try:
        v = int(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{s!r} is not a port number") from None
    if not 0 <= v <= 65535:
        raise argparse.ArgumentTypeError(f"{v} is not a TCP port (0..65535; 0 = any free port)")
    return v


def _handler(s: str) -> str:
    import argparse
    from imubench.station.security import PORT_HANDLERS
    name = s.lower().removesuffix("://")
    if name not in PORT_HANDLERS:
        raise argparse.ArgumentTypeError(f"{s!r} is not a pyserial URL handler to allow ({', '.join(PORT_HANDLERS)}; "
                                         "serial devices, socket:// and rfc2217:// are always allowed)")
    return name


def _port_host(s: str) -> str:
    """--allow-port-host: *, an IP address, or a host name (no scheme, no port)."""
    import argparse
    import ipaddress
    import re
    h = s.strip()
    if h == "*" or re.fullmatch(r"[A-Za-z0-9]([A-Za-z0-9-]{0,62})(\.[A-Za-z0-9]([A-Za-z0-9-]{0,62}))*", h):
        return h
    try:
        ipaddress.ip_address(h.strip("[]"))
        return h
    except ValueError:
        raise argparse.ArgumentTypeError(f"{s!r} is not a host (an IP address or a name, no scheme or port; "
                                         "* any)") from None


def _origin(s: str) -> str:
    import argparse
    from imubench.station.security import origin_authority
    try:
        origin_authority(s)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    return s


def add_web(p) -> None:
    """--http-port, --open and what the page may do, the same for `station` and `calibrate --ui web`."""
    p.add_argument("--http-port", type=_http_port, default=0, metavar="N",
                   help="port of the station page on 127.0.0.1 (0: any free port; the address is printed)")
    p.add_argument("--open", action="store_true", help="open the page in the default browser")
    p.add_argument("--allow-port-handler", type=_handler, action="append", default=[], metavar="NAME",
                   help="let the page open ports of this pyserial URL handler too (spy, loop, hwgrep, alt, cp2110; "
                        "spy:// never with file=); by default only serial devices, socket:// and rfc2217://")
    p.add_argument("--allow-port-host", type=_port_host, action="append", default=[], metavar="HOST",
                   help="let the page open socket:// and rfc2217:// ports on HOST (an IP or a name; * any); "
                        "by default only on this machine, so that no page makes the station connect elsewhere")
    p.add_argument("--allow-origin", type=_origin, action="append", default=[], metavar="URL",
                   help="also serve the page as URL, e.g. http://localhost:9000 for an SSH tunnel whose local "
                        "port differs from --http-port (docs/production.md, 'Who can drive the station page')")


def port_policy(a):
    """The ports the page may open, from --allow-port-handler and --allow-port-host."""
    from imubench.station.security import PortPolicy
    return PortPolicy(handlers=getattr(a, "allow_port_handler", ()), hosts=getattr(a, "allow_port_host", ()))


def register(sub) -> None:
    p = sub.add_parser("station", help="the calibration station page in the browser (idle: choose on the page)",
                       description="Serve the calibration station on 127.0.0.1: a page that guides a person through "
                                   "a session (pictures of every attitude, any order, live stillness, verdict, "
                                   "report). Choose the device, method and options on the page. Works offline.")
    add_web(p)
    p.add_argument("--dir", type=out_dir, metavar="DIR", default=Path("."),
                   help="where the session directories are made")
    p.add_argument("--db", metavar="PATH", help="history database (default: in the user data directory)")
    add_sim(p, "offer the virtual bench on the page (a simulated person presents the attitudes)", lockstep_speed=20.0)
    p.set_defaults(run=run)


def serve_forever(server, open_browser: bool, until=None, then=lambda: None) -> None:
    """Listen, call then() (what the page is for starts once it can be served), print the
    address with its one-time secret, open the browser if asked, and serve until Ctrl-C (or
    until() returns true). Each time a browser trades the secret, the next address is printed."""
    import time
    server.start()
    try:
        then()
        print(f"station page: {server.launch_url}", flush=True)
        print("  (127.0.0.1 only; the secret in the address opens the page once, in one browser: the next "
              "address is printed here; Ctrl-C stops the station)", flush=True)
        server.on_new_url = lambda url: print(f"station page opened in a browser; to open it in another: {url}",
                                              flush=True)
        if open_browser:
            import webbrowser
            if not webbrowser.open(server.launch_url):
                print("could not start a browser: open the address above yourself", file=sys.stderr)
        while until is None or not until():
            time.sleep(0.2)
    finally:
        server.stop()


def serve_page(station, a, until=None, start=lambda: None) -> None:
    """Serve `station` (imubench.station.runner.Station) on 127.0.0.1:--http-port: start()
    once it is bound, then until Ctrl-C (a normal end here) or until() is true. A port that
    cannot be served is a one-line error."""
    from imubench.station.runner import StationError
    from imubench.station.server import Server
    try:
        serve_forever(Server(station, port=a.http_port, allow_origins=getattr(a, "allow_origin", ())), a.open,
                      until=until, then=start)
    except KeyboardInterrupt:
        pass
    except StationError as e:
        raise CommandError(str(e), "give another --http-port, or 0 for any free port") from None


def run(a) -> int:
    from imubench.station.runner import Station
    station = Station(workdir=a.dir, db=a.db, sim_speed=a.sim_speed, sim_seed=a.sim_seed, allow_sim=a.sim,
                      ports=port_policy(a))
    try:
        serve_page(station, a)
    finally:
        station.close()
    return 0
