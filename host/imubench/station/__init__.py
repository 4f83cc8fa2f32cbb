"""The calibration station: a local web page (127.0.0.1) that a person at the bench follows
through a guided session, with live updates (server-sent events).

    state.py      what every page shows, keyed per device (StationState, DeviceBoard)
    presenter.py  WebPresenter: the session's Presenter that writes into that state
    runner.py     Station: starts, stops and resumes sessions, one per device, in threads
    server.py     the Starlette app and its uvicorn server (serve, serve_in_thread)
    security.py   who may drive it (the operator's own browser) and which ports a page may open
    static/       the page itself (HTML, CSS, JS): no CDN, nothing fetched at run time

`imubench station` starts one idle; `imubench calibrate --ui web` starts one with the
session already running (imubench.cli.station, imubench.cli.calibrate).
"""
