"""Figure of a logger bundle's best-estimate trajectory: what the airspeed and q̄ were rebuilt from, and how well.

Top: the reconstructed airspeed with its 1-sigma band, and the receiver's ground
speed against the reconstruction's ground speed at each stamp less the latency
(they differ by the wind). Middle: q̄ with its 1-sigma band (systematic: one set
of air parameters moves it all). Bottom: the receiver's vertical velocity and
the reconstruction's. SI units, as the estimate.
"""

from __future__ import annotations

import matplotlib.pyplot as plt

from cpas_bayes.outputs.figures import MODEL_COLOR as _MODEL

_DATA = "#1f9bd1"


def plot_air_data(estimate, title=""):
    """Three panels of :class:`~cpas_bayes.data.air_reconstruction.AirDataEstimate`; returns the figure."""
    f, r = estimate.frame, estimate.receiver
    t = f["time"].to_numpy()
    fig, axes = plt.subplots(3, 1, figsize=(9, 8.5), sharex=True)
    ax = axes[0]
    v, dv = f["airspeed"].to_numpy(), f["airspeed_sigma"].to_numpy()
    ax.fill_between(t, v - dv, v + dv, color=_MODEL, alpha=0.3, lw=0, label="airspeed ± 1σ (reconstruction)")
    ax.plot(t, v, color=_MODEL, lw=1.2)
    ax.plot(r["time"], r["ground_speed"], "o", ms=3, color=_DATA, label="receiver ground speed")
    ax.plot(r["time"], r["ground_speed_model"], "-", lw=0.8, color="k", label="reconstruction's ground speed")
    ax.set_ylabel("speed [m/s]")
    ax.legend(fontsize=8)
    ax = axes[1]
    q, dq = f["qbar"].to_numpy(), f["qbar_sigma"].to_numpy()
    ax.fill_between(t, q - dq, q + dq, color=_MODEL, alpha=0.3, lw=0, label="q̄ ± 1σ (systematic)")
    ax.plot(t, q, color=_MODEL, lw=1.2)
    ax.set_ylabel("q̄ [Pa]")
    ax.legend(fontsize=8)
    ax = axes[2]
    ax.plot(r["time"], r["v_up"], "o", ms=3, color=_DATA, label="receiver v_up")
    ax.plot(r["time"], r["v_up_model"], "-", lw=0.8, color="k", label="reconstruction (stamp − latency)")
    ax.set_ylabel("vertical velocity [m/s]")
    ax.set_xlabel("time [s]")
    ax.legend(fontsize=8)
    names = ("V0", "γ0", "ψ0", "h0", "wind N (profile offset)", "wind E", "scale", "bias", "latency")
    fmt = ("{:.1f} m/s", "{:.1f}°", "{:.0f}°", "{:.0f} m", "{:+.2f} m/s", "{:+.2f} m/s", "{:.3f}", "{:+.3f} g",
           "{:.3f} s")
    said = ", ".join(f"{n} {f_.format(x)}" for n, f_, x in zip(names, fmt, estimate.phi))
    fig.suptitle(f"{title}: best-estimate trajectory (accelerometer as input, receiver as output)\n{said}",
                 fontsize=9)
    fig.tight_layout()
    return fig
