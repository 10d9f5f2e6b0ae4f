"""Path record and playback in a ``pfma controller`` run (the Multi-Segment Path Planner,
issue 6; the files: ``pfma path``)."""

from __future__ import annotations

from tools.cli.controller.common import max_turn_rad, text


def setup_paths(d, args) -> dict | None:
    """Path store, path id, and a frame hook that starts recording/playback once powered up;
    returns the hook's state for :func:`finish_paths` (None without --record or --play)."""
    if args.record is None and args.play is None:
        return None
    from controller.decision import Status
    from controller.paths import MspMode, PathStore
    store = PathStore(args.path_dir)
    msp = d.rt.by_key["msp"]
    msp.store = store
    wm, key = d.rt.wm, d.rt.wm.access_key
    if args.record is not None:
        path = store.load(args.record) if store.exists(args.record) else store.new(args.record,
                                                                                   note="pfma controller --record")
        settings: dict = {"msp.path_id": path.id, "msp.capture": not args.no_capture,
                    "msp.record_source": 1 if args.record_command else 0}
        start = {"msp.mode": MspMode.RECORD}
        print(f"recording into path {path.name} (id {path.id}) in {store.dir}")
    else:
        path = store.load(args.play)
        settings = {"msp.path_id": path.id}
        if args.speed is not None:
            settings["msp.speed_scale"] = args.speed
        if args.max_turn is not None:
            settings["msp.max_turn_rad"] = max_turn_rad(args.max_turn)
        start = {"cart.mode": 2, "msp.mode": MspMode.PLAY}
        print(f"playing path {path.name} (id {path.id}, {len(path.points)} points) from {store.dir}")
    for name, value in settings.items():
        wm.set_user(name, value, key)
    state = {"started": None, "teach_t": None}

    def hook(rec) -> None:
        if state["started"] is None:
            if d.rt.status("updown") == Status.START_UP_COMPLETE:
                for name, value in start.items():
                    wm.set_user(name, value, key)
                state["started"] = state["teach_t"] = rec.t_s
            return
        if args.record is not None and args.teach_every and rec.t_s - state["teach_t"] >= args.teach_every:
            state["teach_t"] = rec.t_s
            wm.set_user("msp.teach", int(wm.get("msp.teach")) + 1, key)
    d.rt.on_frame.append(hook)
    return state


def finish_paths(d, args, state: dict | None) -> None:
    """End a recording (saved), report a playback."""
    if args.record is None and args.play is None:
        return
    from controller.paths import MspMode, MspResult
    wm = d.rt.wm
    if (state or {}).get("started") is None:
        print("path: never powered up (use --power-up); nothing recorded or played")
        return
    if args.record is not None:
        n = int(wm.get("msp.finished"))
        wm.set_user("msp.mode", MspMode.IDLE, wm.access_key)
        for _ in range(64):  # the planner runs at 20 Hz: a few of its periods
            d.frame()
            if int(wm.get("msp.finished")) > n:
                break
        d.rt.by_key["msp"].wait_saved()
        for _ in range(4):
            d.frame()
        saved = d.rt.by_key["msp"].last_saved
        res = MspResult.NAMES.get(int(wm.get("msp.result")), "?")
        if saved is not None:
            print(f"path {saved.name}: {len(saved.points)} points, {saved.length_m:.3f} m, revision {saved.revision} "
                  f"({res})")
        else:
            print(f"path {args.record}: not saved ({res})")
    else:
        v = wm.get_task_inputs(("msp.state", "msp.segment", "msp.segments", "msp.result", "msp.finished"))
        if int(v["msp.state"]) == MspMode.PLAY:
            print(f"path {args.play}: still playing, segment {int(v['msp.segment'])} of {int(v['msp.segments'])} "
                  f"(run longer: --duration)")
        else:
            print(f"path {args.play}: playback ended ({MspResult.NAMES.get(int(v['msp.result']), '?')}): "
                  f"{text(wm.get('msp.result_text'))}")

