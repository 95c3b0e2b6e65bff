"""The diagnosis for people: a headline, the largest gaps, the attribution table, and plots.

A recording with the attitude also gets a few lines for the attitude-aided part (.attitude): the vector
baseline's field, residual RMS per axis and rows used/skipped, then each effect tested on its residual
with p, the held-out RMS before/after and the share of variance explained, and its size per axis with
the 95% interval (units stated).

``text(diag)`` is the report printed by ``mkc-stream diagnose``; ``write(diag, directory)``
saves it as ``report.md`` beside PNG plots (needs matplotlib, the ``plot`` extra):
residual against time with the replicas' 5-95% band, the sphere map of the mean residual,
the residual spectrum against the replicas', and the residual against each aux signal.
"""
from __future__ import annotations

import pathlib

import numpy as np

HEADLINES = {
    "no_gap": "NO GAP: the simulator reproduces this recording (gap index at its null level, no matched test fired).",
    "explained": "EXPLAINED: the gap is closed by {effects}.",
    "partially_explained": "PARTLY EXPLAINED: {effects} close part of the gap; the rest is not in the library.",
    "unexplained": "UNEXPLAINED: there is a gap, and no effect of the library closes it.",
    "baseline_rejected": "BASELINE REJECTED: the calibrator would not accept this recording's calibration ({reason}), "
                         "so no gap is read from it.\n  still tested  : {tested}: {on_testable}.",
}

#: what the restricted test found, in the rejected baseline's headline
ON_TESTABLE = {
    None: "nothing to compare",
    "no_gap": "no gap there",
    "explained": "a gap there, explained by {effects}",
    "partially_explained": "a gap there, partly explained by {effects}",
    "unexplained": "a gap there that no effect of the library closes",
}


def _inclination_text(b) -> str:
    """', inclination ...' of the baseline, or why it is not given; '' without an accelerometer."""
    inc = b.get("inclination_deg")
    if inc is None and b.get("field_gravity_angle_deg") is None:
        return ""
    if inc is not None and inc == inc:
        return f", inclination {inc:.1f} deg (below the horizontal, positive down)"
    return (f", inclination not determined (the fitted field-to-gravity angle, "
            f"{b.get('field_gravity_angle_deg', float('nan')):.1f} deg, lies outside 0-180)")


def _fmt(x, nd=3):
    return "-" if x is None or not np.isfinite(x) else f"{x:.{nd}g}"


def _grouped(pairs):
    """[(reason, [names])] in first-seen order: one line per reason, not per name."""
    out = {}
    for name, why in pairs:
        out.setdefault(why, []).append(name)
    return list(out.items())


def _vec(v, nd=3) -> str:
    return "(" + ", ".join(_fmt(x, nd) for x in v) + ")"


def _field_text(f) -> str:
    if f.get("model") == "unit field":
        return f"a unit field, inclination {f['inclination_deg']:.1f} deg estimated (no position; residual not in uT)"
    if f.get("intensity") is not None and f.get("inclination_deg") is not None:
        return (f"{f.get('model')} {f['intensity']:.2f} uT, inclination {f['inclination_deg']:.1f} deg "
                f"({f.get('source')})")
    return f"{f.get('model')} ({f.get('source')})"


def attitude_lines(att) -> list:
    """The attitude-aided part (.attitude): its baseline, then each effect tested with its figures."""
    if att is None:
        return []
    if not att["ran"]:
        b = att.get("baseline") or {}
        used = (f" ({b['samples']} rows with attitude, {b['skipped']} skipped)" if "samples" in b else "")
        return [f"  attitude-aided: not run: {att['reason']}{used}"]
    b = att["baseline"]
    u = b["unit"] if b["field"].get("model") != "unit field" else f"{b['unit']} (unit-field scale)"
    L = [f"  attitude-aided: vector baseline m = A R(q)^T h + b against {_field_text(b['field'])}",
         f"                  residual RMS {_vec(b['residual_rms'])} {u} (x, y, z; robust sd "
         f"{_vec(b['residual_robust_sd'])}), {b['samples']} rows used, {b['skipped']} skipped"
         + (f" ({b['skipped_reason']})" if b.get("skipped") else "")]
    if b.get("held"):
        L.append(f"                  held at their prior: {', '.join(b['held'])}")
    found = att["found"]
    L.append(f"                  found (p < {att['level']:g} and a lower held-out residual): "
             + (", ".join(found) if found else "none"))
    for e in att["effects"]:
        if not e["testable"]:
            L.append(f"    {e['name']:20s} not testable: {e['reason']}")
            continue
        h, sz = e["held_out"], e["size"]
        L.append(f"    {e['name']:20s} {'FOUND' if e['found'] else 'not found':9s} p {_fmt(e['p_value'], 2)} (shift test); "
                 f"held-out RMS "
                 f"{_vec(h['rms_before'])} -> {_vec(h['rms_after'])} {h['unit']}, "
                 f"{h['variance_explained']:.1%} of its variance explained")
        ci = ", ".join(f"{_fmt(v)} [{_fmt(lo)}, {_fmt(hi)}]" for v, (lo, hi) in zip(sz["value"], sz["ci95"]))
        extra = ""
        if "delay_s" in e:
            d = e["delay_s"]
            extra = "; delay " + (e.get("delay_note") or "not determined" if d is None
                                  else f"{d * 1e3:.0f} ms (the magnetometer sees the current this late)" if d >= 0
                                  else f"{d * 1e3:.0f} ms (the logged current is {-d * 1e3:.0f} ms late: "
                                       "a filtered or late-logged sensor)")
        if "lag_s" in e:
            extra = f"; thermal lag {e['lag_s']:g} s"
        L.append(f"    {'':20s} size {ci} {sz['unit']} (x, y, z; 95%){extra}")
        if e["name"] in att.get("ambiguous_with", {}):
            gain = e["held_out"].get("adds_given_others")
            L.append(f"    {'':20s} adds {_fmt(None if gain is None else 100 * gain, 2)}% of the held-out variance given "
                     f"{', '.join(att['ambiguous_with'][e['name']])}: the data cannot tell them apart")
        if sz.get("note"):
            L.append(f"    {'':20s} note: {sz['note']}")
    for note in b.get("notes") or ():
        L.append(f"    note: {note}")
    return L


def headline(diag) -> str:
    effects = " + ".join(diag.selected) or "-"
    scope = diag.info.get("scope") or {}
    on = ON_TESTABLE[scope.get("verdict_on_testable")].format(effects=effects)
    return HEADLINES[diag.verdict].format(effects=effects, reason=scope.get("calibration_reason"),
                                          tested=scope.get("tested"), on_testable=on)


def text(diag, source="") -> str:
    L = []
    info = diag.info
    L.append(f"mkc-stream diagnose: {source}".rstrip(": "))
    L.append(f"  {headline(diag)}")
    basis = getattr(diag, "basis", None)
    if basis is not None and basis.rule:
        # the figures the verdict was decided from, beside it
        L.append(f"  because       : {basis.rule}")
        for note in basis.notes:
            L.append(f"                  then {note}")
    att = getattr(diag, "attitude", None)
    att = None if att is None else att.to_json()
    if att is not None and att["ran"]:
        L.append("  with attitude : the attitude-aided vector residual was tested too (below): "
                 + (f"found {', '.join(att['found'])}" if att["found"] else "no effect found"))
    dec = f", decimated by {info['decimation']}" if info.get("decimation", 1) > 1 else ""
    L.append(f"  recording     : {info['samples']} samples over {info['duration_s']:.1f} s{dec}; "
             f"aux used: {', '.join(info['aux_used']) or 'none'}")
    b = info["baseline"]
    cal = b.get("calibration") or {}
    # a rejected calibration's field, noise and bursts are read from the fit the calibrator refuses:
    # figures of that fit, not measurements of the sensor
    rejected = bool(cal) and not cal["accepted"]
    L.append(f"  baseline      : {'(the rejected fit; not measurements) ' if rejected else ''}"
             f"field {b['field']:.4g} {info['unit']}, white noise {b['noise']:.3g} {info['unit']}, "
             f"bursts {b['burst_fraction']:.1%}"
             + _inclination_text(b))
    if cal:
        cov = (cal.get("quality") or {}).get("coverage")
        L.append("  calibration   : " + (f"accepted by the calibrator (sphere coverage {cov:.0%})" if cal["accepted"]
                                        else f"REJECTED by the calibrator: {cal['reason']}"))
    L += attitude_lines(att)
    L.append(f"  gap index     : {_fmt(diag.gap_before)} (held-out; no-gap level 1, alarm above {_fmt(diag.threshold)})"
             + (f" -> {_fmt(diag.gap_after)} with {' + '.join(diag.selected)}" if diag.selected else ""))
    mt = info.get("matched_tests") or {}
    if mt.get("fired"):
        L.append(f"  matched tests : fired for {', '.join(mt['fired'])} (each at level {mt['level']:.2g})")
    gt = info.get("gyro_timing")
    if gt:
        L.append(f"  gyro timing   : magnetometer late by {gt['delay_ms']:.2f} +- {gt['se_ms']:.2f} ms against the "
                 f"gyroscope (t = {gt['t']:.1f})" if gt["testable"] else f"  gyro timing   : not testable ({gt['reason']})")
    if diag.verdict != "no_gap" and info.get("detected_by") == "matched tests":
        # the gap index is at its null level: shrinks are on the matched evidence
        L.append(f"  shrink        : {_fmt(diag.shrink, 2)} of the fired matched evidence removed "
                 "(the gap index alone is below its alarm)")
    elif diag.verdict != "no_gap" and (info.get("scope") or {}).get("verdict_on_testable", "") != "no_gap":
        L.append(f"  shrink        : {_fmt(diag.shrink, 2)} of the excess held-out gap closed")
    left = info.get("aux_left") or {}
    if left.get("still_followed"):
        ts = ", ".join(f"{a} (t = {left['tests'][a]['t']:.1f})" for a in left["still_followed"])
        L.append(f"  not complete  : given {' + '.join(diag.selected)}, the residual still follows {ts}")
    if diag.ambiguous_with:
        L.append(f"  ambiguous with: {', '.join(diag.ambiguous_with)} (the data cannot tell these apart)")
    L.append("")
    L.append("  largest gaps (z = real against the replicas, in replica standard deviations)")
    L.append(f"    {'family':14s} {'channel':8s} {'where':52s} {'z':>7s}")
    for w in diag.where[:10]:
        L.append(f"    {w['family']:14s} {w['channel']:8s} {w['bin'][:52]:52s} {w['z']:7.1f}")
    L.append("")
    L.append("  attribution (held-out blocks; shrink = fraction of the excess gap closed, 90% interval)")
    L.append(f"    {'effect':24s} {'status':13s} {'shrink':>7s} {'interval':>15s}  magnitude")
    for r in diag.effects:
        if not r.testable:
            continue
        ci = f"[{r.shrink_ci[0]:.2f}, {r.shrink_ci[1]:.2f}]" if r.shrink_ci else ""
        mag = ""
        if r.magnitude:
            mag = f"{_fmt(r.magnitude['value'])} {r.magnitude.get('unit', '')}"
            if r.magnitude_ci and r.magnitude_ci.get("value"):
                lo, hi = r.magnitude_ci["value"]
                mag += f" [{_fmt(lo)}, {_fmt(hi)}]"
        L.append(f"    {r.name:24s} {r.status:13s} {_fmt(r.shrink, 2):>7s} {ci:>15s}  {mag}")
    bad = [(r.name, r.why_implausible) for r in diag.effects if r.status == "implausible" and r.why_implausible]
    if bad:
        L.append("  implausible, because:")
        for why, names in _grouped(bad):
            L.append(f"    {', '.join(names)}: {why}")
    nt = [r for r in diag.effects if not r.testable]
    off = (info.get("scope") or {}).get("statistics_not_testable") or {}
    if nt or off:
        L.append("")
        L.append("  not testable with this recording (not the same as absent):")
        if att is not None and att["ran"]:
            tested = [e["name"] for e in att["effects"] if e["testable"]]
            if tested:
                L.append(f"    ({', '.join(tested)}: tested on the attitude-aided residual above)")
        for why, names in _grouped([(r.name, r.reason) for r in nt]):
            L.append(f"    {names[0]:24s} {why}" if len(names) == 1 else f"    {', '.join(names)}:")
            if len(names) > 1:
                L.append(f"      {why}")
        for why, fams in _grouped(off.items()):
            L.append(f"    statistics {', '.join(fams)}:")
            L.append(f"      {why}")
    if diag.excluded:
        L.append(f"  left out of the library on request: {', '.join(diag.excluded)}")
        for d in getattr(diag, "dropped", ()):
            if d["name"] not in diag.excluded and d["reason"].startswith("left out with"):
                L.append(f"    and {d['name']}: {d['reason']}")
    L.append(f"  ({info['replicas']} replicas, profile {info['profile']}, {info['seconds']:.1f} s)")
    return "\n".join(L)


def _band(x, q=(5, 95)):
    return np.nanpercentile(x, q[0], axis=0), np.nanpercentile(x, q[1], axis=0)


def _smooth(x, w):
    from ..sim.trajectory import moving_average

    return moving_average(x[:, None], w)[:, 0]


def plots(diag, directory) -> list:
    """Save the PNG plots; returns their paths (empty without matplotlib)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return []
    from ..plots import save_figure

    out = pathlib.Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    eng = diag.engine
    ev = diag.evaluations["baseline"]
    frame, unit = eng.frame, eng.frame.unit
    t = frame.t - frame.t[0]
    e = np.where(ev.inlier[:, 0], ev.e[:, 0], np.nan)
    reps = np.where(np.abs(ev.rep_e[:, :, 0]) < 4 * eng.base.sigma[0], ev.rep_e[:, :, 0], np.nan)
    w = max(5, frame.n // 200)
    paths = []

    def fill(a):
        return np.where(np.isfinite(a), a, 0.0)

    fig, ax = plt.subplots(figsize=(10, 4))
    sm = np.array([_smooth(fill(r), w) for r in reps])
    lo, hi = _band(sm)
    ax.fill_between(t, lo, hi, color="0.8", label="replicas 5-95%")
    ax.plot(t, _smooth(fill(e), w), color="C3", lw=1, label="real (baseline)")
    fin = diag.evaluations.get("final")
    if diag.selected and fin is not None:
        ef = np.where(fin.inlier[:, 0], fin.e[:, 0], 0.0)
        ax.plot(t, _smooth(ef, w), color="C2", lw=1, label="real with " + " + ".join(diag.selected))
    ax.set_xlabel("time (s)")
    ax.set_ylabel(f"norm residual ({unit}), {w}-sample mean")
    ax.set_title(headline(diag), fontsize=9)
    ax.legend(fontsize=8)
    paths.append(out / "residual_time.png")
    fig.tight_layout()
    save_figure(fig, paths[-1])
    plt.close(fig)

    v = ev.fit.v
    lon = np.degrees(np.arctan2(v[:, 1], v[:, 0]))
    fig, ax = plt.subplots(figsize=(8, 4))
    hb = ax.hexbin(lon, v[:, 2], C=fill(e), reduce_C_function=np.mean, gridsize=30, cmap="coolwarm")
    lim = float(np.nanpercentile(np.abs(np.ma.filled(hb.get_array(), np.nan)), 98)) or 1.0
    hb.set_clim(-lim, lim)
    fig.colorbar(hb, ax=ax, label=f"mean norm residual ({unit})")
    ax.set_xlabel("longitude of the calibrated field (deg)")
    ax.set_ylabel("z of the calibrated field direction (equal area)")
    ax.set_title("where on the sphere the residual departs", fontsize=9)
    paths.append(out / "sphere.png")
    fig.tight_layout()
    save_figure(fig, paths[-1])
    plt.close(fig)

    from scipy.signal import welch

    fs = 1.0 / frame.dt0
    nper = min(1024, frame.n // 8)
    f, P = welch(fill(e), fs=fs, nperseg=nper)
    Pr = np.array([welch(fill(r), fs=fs, nperseg=nper)[1] for r in reps])
    lo, hi = _band(Pr)
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.fill_between(f[1:], lo[1:], hi[1:], color="0.8", label="replicas 5-95%")
    ax.loglog(f[1:], P[1:], color="C3", label="real")
    ax.set_xlabel("frequency (Hz)")
    ax.set_ylabel(f"PSD of the norm residual ({unit}^2/Hz)")
    ax.legend(fontsize=8)
    paths.append(out / "spectrum.png")
    fig.tight_layout()
    save_figure(fig, paths[-1])
    plt.close(fig)

    for name, x in frame.aux.items():
        edges = np.unique(np.quantile(x, np.linspace(0, 1, 21)))
        if edges.size < 3:
            continue
        idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, edges.size - 2)
        centres = 0.5 * (edges[1:] + edges[:-1])

        def binned(y):
            ok = np.isfinite(y)
            s = np.bincount(idx[ok], weights=y[ok], minlength=edges.size - 1)
            c = np.bincount(idx[ok], minlength=edges.size - 1)
            return np.where(c > 0, s / np.maximum(c, 1), np.nan)
        br = np.array([binned(r) for r in reps])
        lo, hi = _band(br)
        fig, ax = plt.subplots(figsize=(6, 4))
        ax.fill_between(centres, lo, hi, color="0.8", label="replicas 5-95%")
        ax.plot(centres, binned(e), "o-", color="C3", label="real")
        ax.set_xlabel(name)
        ax.set_ylabel(f"mean norm residual ({unit})")
        ax.legend(fontsize=8)
        paths.append(out / f"aux_{name}.png")
        fig.tight_layout()
        save_figure(fig, paths[-1])
        plt.close(fig)
    return paths


def write(diag, directory, source="") -> list:
    """report.md (the text report and the plot list) and the PNG plots in ``directory``."""
    out = pathlib.Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    paths = plots(diag, out)
    body = ["# Sim-to-real gap diagnosis", "", "```", text(diag, source), "```", ""]
    if paths:
        body += [f"![{p.stem}]({p.name})" for p in paths]
    else:
        body.append("(plots need matplotlib: pip install 'mkc-stream[plot]')")
    (out / "report.md").write_text("\n".join(body) + "\n", encoding="utf-8")
    return [out / "report.md"] + paths
