"""What a browser may change: every state value a client sends is checked before the server applies it.

trame applies a client's ``trame.state.update`` to the server state as it comes; the page's widgets only
ever send the values below, but any client on the websocket can send anything.  :func:`state_rules`
names each key a client may set with its check (type, length, range, allowed set); :func:`install`
puts the check in front of trame's update: an update with an unknown key or a bad value is refused
whole, logged as one line, and the client's page is reset to the server's values; a call of a controller
with arguments it does not take is refused the same way.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable

log = logging.getLogger(__name__)

Check = Callable[[object], str | None]


def text(max_len: int) -> Check:
    def check(v):
        if v is None or (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)):
            return None
        if not isinstance(v, str):
            return f"expected text, got {type(v).__name__}"
        return None if len(v) <= max_len else f"text longer than {max_len} characters"

    return check


def number(lo: float, hi: float) -> Check:
    def check(v):
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            return f"expected a number, got {type(v).__name__}"
        return None if math.isfinite(v) and lo <= v <= hi else f"{v!r} is outside {lo:g} ... {hi:g}"

    return check


def one_of(allowed) -> Check:
    allowed = list(allowed)

    def check(v):
        return (
            None
            if isinstance(v, (str, int)) and not isinstance(v, bool) and v in allowed
            else (f"{str(v)[:40]!r} is not one of {', '.join(map(str, allowed))}")
        )

    return check


def subset_of(allowed) -> Check:
    allowed = list(allowed)

    def check(v):
        if not isinstance(v, list) or len(v) > len(allowed):
            return "expected a list of choices"
        bad = [x for x in v if not isinstance(x, str) or x not in allowed]
        return f"{str(bad[0])[:40]!r} is not one of {', '.join(allowed)}" if bad else None

    return check


def sort_spec(columns) -> Check:
    columns = list(columns)

    def check(v):
        if not isinstance(v, list) or len(v) > 3:
            return "expected at most 3 sort keys"
        for s in v:
            if not isinstance(s, dict) or s.get("key") not in columns or s.get("order", "asc") not in ("asc", "desc"):
                return f"{str(s)[:60]} is not a column with order asc or desc"
        return None

    return check


def equal_to(value) -> Check:
    return lambda v: None if v == value else f"only {value!r} may be set"


def state_rules(p) -> dict[str, Check]:
    """The client-settable keys of Platform ``p`` and their checks."""
    from spinecohort.web.app import FLAG_CHOICES, PAGE_SIZES

    lim = float(p.state.slider_lim)
    rules: dict[str, Check] = {
        "f_other": text(500),
        "f_gap": subset_of([c["value"] for c in p.state.gap_choices]),
        "f_kind": one_of(p.state.kind_choices),
        "model_input": text(64),
        "overlay_input": text(64),
        "message": equal_to(""),  # the message's close button
        "page": number(1, 1e6),
        "per_page": one_of(PAGE_SIZES),
        "sort_by": sort_spec([c for c in p.columns if c != "weights"]),
    }
    for c in p.ranges:
        rules[f"f_{c}_lo"] = rules[f"f_{c}_hi"] = text(32)
    for f in p.data.flags:
        rules[f"f_{f}"] = one_of(FLAG_CHOICES)
    for k in ("PI", "PT", "SS", "LL"):
        rules[f"pat_{k}"] = text(16)
    for i in range(p.n_sliders):
        rules[f"w_{i}"] = number(-lim, lim)
    return rules


def refusal(rules: dict[str, Check], changes: dict) -> str | None:
    """Why ``changes`` (key -> value from a client) is refused, or None when every key is allowed and
    every value passes its check."""
    for k, v in changes.items():
        check = rules.get(k)
        if check is None:
            return f"{str(k)[:40]!r} is not a value the page sets"
        why = check(v)
        if why:
            return f"{k}: {why}"
    return None


def install(server, rules: dict[str, Check], on_refuse: Callable[[str], None] | None = None) -> None:
    """Check every client state update of ``server`` (this process's trame server) against ``rules``.

    trame has one protocol class per process; each session of the platform is its own process, so the
    check replaces the update entry point of this process only."""
    from trame_server.protocol import CoreServer
    from wslink import register

    applied = CoreServer.update_state

    @register("trame.state.update")
    def update_state(self, changes):
        try:
            values = {c["key"]: c.get("value") for c in changes}
        except (TypeError, KeyError, AttributeError):
            values, why = {}, "not a list of {key, value} changes"
        else:
            why = refusal(rules, values)
        if why is None:
            return applied(self, changes)
        log.warning("refused a state update from a browser: %s", why)
        keys = [k for k in values if isinstance(k, str) and k in rules]
        if keys:  # the client shows the refused value: send it the server's
            self.force_push_state(*keys)
        if on_refuse:
            with server.state:
                on_refuse(why)
        return None

    CoreServer.update_state = update_state
    called = CoreServer.trigger

    @register("trame.trigger")
    async def trigger(self, name, args, kwargs):
        try:
            return await called(self, name, args, kwargs)
        except (TypeError, ValueError) as exc:  # arguments no button of the page sends
            log.warning("refused a call from a browser: %s: %s", str(name)[:40], str(exc)[:200])
            return None

    CoreServer.trigger = trigger
