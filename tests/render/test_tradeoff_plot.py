"""The trade-off plot: the ``y = tau`` line is drawn on the measured-error panel, the one it
is read against (it was on the resident-MiB panel); no GL."""

from __future__ import annotations

import matplotlib.pyplot as plt

from render.pipeline import ERROR_PANEL, TradeoffRow, plot_tradeoff, tradeoff_figure


def _row(tau: float, err: float) -> TradeoffRow:
    return TradeoffRow(
        tau=tau, metric="qiu", triangles=1000, patches=4, selection_ms=1.0, frame_ms=2.0,
        reference_frame_ms=5.0, reference_triangles=8000, max_screen_error_px=err,
        p99_screen_error_px=err / 2, mean_screen_error_px=err / 4, samples_in_view=100,
        psnr_db=40.0, changed_share=0.1, crack_pixels=0, resident_bytes=3 << 20,
        loaded_bytes=3 << 20, gpu_bytes=1 << 20, clamped=0,
    )  # fmt: skip


def test_the_tau_line_is_on_the_error_panel(tmp_path):
    rows = [_row(0.5, 0.4), _row(1.0, 2.1), _row(4.0, 5.0)]
    fig = tradeoff_figure(rows, "t")
    try:
        with_tau = [
            a.get_title() for a in fig.axes for ln in a.get_lines() if ln.get_label() == "tau"
        ]
        assert with_tau == [ERROR_PANEL]
        err = next(a for a in fig.axes if a.get_title() == ERROR_PANEL)
        tau_line = next(ln for ln in err.get_lines() if ln.get_label() == "tau")
        assert list(tau_line.get_xdata()) == list(tau_line.get_ydata()) == [0.5, 1.0, 4.0]
        labels = {ln.get_label() for ln in err.get_lines()}
        assert {"qiu max", "qiu p99", "tau"} <= labels
    finally:
        plt.close(fig)
    plot_tradeoff(rows, tmp_path / "t.png")
    assert (tmp_path / "t.png").stat().st_size > 10_000
