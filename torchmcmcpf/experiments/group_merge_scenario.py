"""The simulated tracks of Septier, Pang, Godsill and Carmi (2009, paper 004), Fig. 3: two
groups of two targets on converging courses merge at step 46, observed by a thresholded
100 x 100 pixel sensor (:mod:`torchmcmcpf.scenarios.group_merge`).

This study draws the scenario only (the filter of paper 004 is a separate study). Writes

- ``tracks.png``: left, the true tracks (Fig. 3), coloured by group before the merge, with
  the start of each track and the merge marked; right, run 0's detections summed over all
  frames, the tracks as the sensor sees them;
- ``metrics.json``: the sensor (``P_d,1``, ``P_fa``, SNR from eq. 41), the geometry (distance
  between the two groups' centres at steps 1, 45, 46 and 110, smallest distance between two
  targets), the empirical detection and false alarm rates over all runs, the mean number of
  detections per frame, the structure per step and the simulation time.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..models.group import group_structures
from ..scenarios.group_merge import group_merge
from ._figures import pyplot, save_figure
from ._options import RunOptions
from ._study import Settings, StepTimer, Study, generator, option


@dataclass(frozen=True)
class MergeSettings(Settings):
    """The settings of :class:`GroupMerge` (full values; the second of each pair: ``--quick``)."""

    runs: int = option(40, 2, help="observation sets")
    slots: int = option(4, help="N_max target slots")


class GroupMerge(Study[MergeSettings]):
    """Fig. 3 of paper 004: the scenario only (module docstring)."""

    name = "group-merge-scenario"
    description = "Septier et al. 2009 Fig. 3: two groups of two targets merge at step 46 (thresholded pixels)"
    outputs = ("metrics.json", "tracks.png")

    def summary(self, payload: dict) -> str:
        """The headline table printed by ``reproduce``: the sensor (model against the simulated
        rates) and the geometry of the merge.
        """
        gap = payload["group_centre_distance_m"]
        rows = [
            ("runs x steps", f"{payload['runs']} x {payload['steps']} (merge at step {payload['merge_step']})",
             "110 steps, merge at 46"),
            ("P_d,1: model / simulated", f"{float(payload['p_d1']):.3f} / {float(payload['empirical_p_d1']):.3f}", "-"),
            ("P_fa: model / simulated", f"{float(payload['p_fa']):.4f} / {float(payload['empirical_p_fa']):.4f}",
             "-"),
            ("SNR [dB], eq. 41", f"{float(payload['snr_db']):.1f}", f"{payload['snr_db_stated_by_paper']:g}"),
            ("detections per frame", f"{float(payload['detections_per_frame']):.1f}", "-"),
            ("group centres apart at steps 1 / 45 / 46 / 110 [m]",
             " / ".join(f"{float(gap[k]):.0f}" for k in ("step_1", "step_45", "step_46", "step_110")), "-"),
            ("closest two targets [m]", f"{float(payload['min_target_distance_m']):.0f}", "-"),
        ]
        return "\n".join(["| quantity | this run | paper |", "| --- | --- | --- |",
                          *(f"| {a} | {b} | {c} |" for a, b, c in rows)])

    def compute(self, settings: MergeSettings, options: RunOptions) -> dict:
        """Simulate and draw the scenario (module docstring); writes into ``options.out``."""
        plt = pyplot()
        runs, slots, device = settings.runs, settings.slots, options.device
        gen = generator(device, options.seed)
        with StepTimer(device, 110) as timer:
            scn = group_merge(runs, generator=gen, num_slots=slots)
        pos = scn.positions[:, 0].cpu()  # (T, K, 2), shared by every run
        t_max = pos.shape[0]
        m = scn.merge_step
        centre_gap = (pos[:, :2].mean(1) - pos[:, 2:4].mean(1)).norm(dim=-1)
        d = (pos[:, :4].unsqueeze(1) - pos[:, :4].unsqueeze(2)).norm(dim=-1) + 1e12 * torch.eye(4)

        idx = scn.sensor.pixel_index(scn.truth, scn.exists)  # (T, B, K)
        flat = scn.frames.reshape(t_max, runs, -1)
        hits = torch.gather(flat, 2, idx.clamp(min=0))[idx >= 0].double()
        on_target = torch.zeros_like(flat).scatter_(2, idx.clamp(min=0), idx >= 0)
        fa_rate = (flat & ~on_target).sum().double() / (~on_target).sum()

        fig, axes = plt.subplots(1, 2, figsize=(13, 6))
        ax = axes[0]
        colours = ["tab:blue", "tab:blue", "tab:red", "tab:red"]
        for k in range(4):
            ax.plot(pos[: m + 1, k, 0], pos[: m + 1, k, 1], color=colours[k], lw=1.2,
                    label="group 1 (steps 1-45)" if k == 0 else ("group 2 (steps 1-45)" if k == 2 else None))
            ax.plot(pos[m:, k, 0], pos[m:, k, 1], color="tab:purple", lw=1.2,
                    label="merged group (steps 46-110)" if k == 0 else None)
            ax.plot(pos[0, k, 0], pos[0, k, 1], "o", color=colours[k], ms=4)
        ax.plot(pos[m, :4, 0], pos[m, :4, 1], "kx", ms=7, label="targets at step 46 (merge)")
        ax.set_xlim(0, 5000)
        ax.set_ylim(0, 5000)
        ax.set_aspect("equal")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.set_title("ground truth: two groups of two targets merge\n(Septier et al. 2009, Fig. 3)", fontsize=10)
        ax.legend(loc="upper left", fontsize=8)
        ax = axes[1]
        acc = scn.frames[:, 0].sum(0).cpu().numpy()
        ax.imshow(acc, origin="lower", extent=(0, 5000, 0, 5000), cmap="gray_r", vmax=max(2, acc.max()))
        ax.set_xlabel("x [m]")
        ax.set_title(f"run 0: detections summed over {t_max} frames\n"
                     f"(P_d,1 = {scn.sensor.p_d1:.2f}, P_fa = {scn.sensor.p_fa:g})", fontsize=10)
        save_figure(fig, options.out, "tracks.png")

        table = group_structures(scn.labels.shape[-1])
        payload = {
            "runs": runs,
            "num_slots": slots,
            "steps": t_max,
            "merge_step": m + 1,
            "p_d1": scn.sensor.p_d1,
            "p_fa": scn.sensor.p_fa,
            "snr": scn.sensor.snr,
            "snr_db": scn.sensor.snr_db,
            "snr_db_stated_by_paper": 17.0,
            "group_centre_distance_m": {"step_1": centre_gap[0], "step_45": centre_gap[m - 1],
                                        "step_46": centre_gap[m], "step_110": centre_gap[-1]},
            "min_target_distance_m": d.min(),
            "empirical_p_d1": hits.mean(),
            "empirical_p_fa": fa_rate,
            "detections_per_frame": scn.frames.double().sum((-1, -2)).mean(),
            "structure_per_step": [table[i].tolist() for i in scn.structure[:, 0].tolist()],
            "simulation_seconds": timer.seconds,
        }
        return payload


STUDY = GroupMerge()
