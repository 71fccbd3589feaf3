//! The report `fleet up` writes from the server's summary and events (the event and summary
//! types live with the server, in `fleet-mission`'s `events`).

use fleet_math::process::truth::TruthSource;
pub use fleet_mission::events::*;
use fleet_mission::server::Counters;
use std::collections::BTreeMap;

/// Why a networked run differs from the offline loop, from what the server reported: each
/// vehicle held out of the allocation (and why), late batches, refusals and lost batches.
fn differences(events: &[ServerEvent], c: &Counters) -> String {
    let mut why: Vec<String> = vec![];
    // Per vehicle, how often it was left out, and why (operator modes, lost autopilots).
    let mut held: BTreeMap<&str, BTreeMap<String, u32>> = BTreeMap::new();
    for e in events {
        match e {
            ServerEvent::Hold {
                vehicle,
                held: true,
                mode,
            } => {
                let why = if mode.contains("(Lost)") {
                    "autopilot lost".to_string()
                } else if mode.is_empty() {
                    "held".to_string()
                } else {
                    format!("mode {}", mode.split(" (").next().unwrap_or(mode))
                };
                *held.entry(vehicle).or_default().entry(why).or_default() += 1;
            }
            ServerEvent::Late { vehicle, epoch, .. } => why.push(format!(
                "{vehicle}'s batch of epoch {epoch} came late: the epoch was assimilated without it and the model \
                    re-fitted when it came (plans made in between differ from the offline loop's)"
            )),
            ServerEvent::Refused {
                vehicle, seq, detail, ..
            } => why.push(format!(
                "{vehicle}'s batch {seq} was \
                refused: {detail}"
            )),
            ServerEvent::Lost { vehicle, seqs } => why.push(format!(
                "{vehicle}'s batches {seqs:?} were lost with the \
                journal"
            )),
            _ => {}
        }
    }
    let times = |n: u32| {
        if n == 1 {
            "once".to_string()
        } else {
            format!("{n} times")
        }
    };
    for (v, reasons) in held.iter().rev() {
        let list = reasons
            .iter()
            .map(|(r, n)| format!("{r} {}", times(*n)))
            .collect::<Vec<_>>()
            .join(", ");
        why.insert(
            0,
            format!(
                "{v} was left out of the allocation ({list}): the offline loop allocates every vehicle every epoch"
            ),
        );
    }
    if c.forced > 0 && !why.iter().any(|w| w.contains("late")) {
        why.push(format!("{} epochs were assimilated without a late vehicle", c.forced));
    }
    if why.is_empty() {
        return "Why: nothing the server reported (no hold, late batch, refusal or loss) explains it; a vehicle that \
            sensed away from its planned place (its log counts `off_target`) would, and otherwise it is a defect to \
            report.\n"
            .into();
    }
    format!(
        "Why:\n\n{}\n",
        why.iter().map(|w| format!("- {w}")).collect::<Vec<_>>().join("\n")
    )
}

/// "850 B", "12.3 kB".
fn bytes_text(b: f64) -> String {
    if b < 1000.0 {
        format!("{b:.0} B")
    } else {
        format!("{:.1} kB", b / 1000.0)
    }
}

/// "every step", "every 5 steps".
fn every(n: usize, unit: &str) -> String {
    if n == 1 {
        format!("every {unit}")
    } else {
        format!("every {n} {unit}s")
    }
}

/// "1st", "2nd", "5th", "11th", "22nd".
fn ordinal(n: usize) -> String {
    let suffix = match (n % 10, n % 100) {
        (_, 11..=13) => "th",
        (1, _) => "st",
        (2, _) => "nd",
        (3, _) => "rd",
        _ => "th",
    };
    format!("{n}{suffix}")
}

/// What the mission report's sections read.
struct MissionReport<'a> {
    mission: &'a fleet_mission::config::MissionConfig,
    summary: &'a ServerSummary,
    offline: Option<&'a crate::experiment::team::TeamOutcome>,
    /// The first step every team has data at (the boats' first sample).
    from: usize,
    md: String,
}

/// The mean of `v` from step `k` on.
/// The mean of the scored steps from step `k` on (a step whose truth had no value is not).
fn mean_from(v: &[f64], k: usize) -> f64 {
    fleet_math::fusion::mean_scored(&v[k.min(v.len())..])
}

/// The report `fleet up` writes: with a truth, the networked mission beside the offline loop
/// on the same truth and seed (which it must equal with simulated sensors), the single-kind
/// teams; with or without one, the held-out readings' figures (when some were held out) and
/// the fleet's statistics.
pub fn write_mission_report(
    dir: &std::path::Path,
    mission: &fleet_mission::config::MissionConfig,
    summary: &ServerSummary,
    offline: Option<&crate::experiment::team::TeamOutcome>,
    grid: &fleet_math::grid::Grid,
    command: &str,
    events: &[ServerEvent],
) -> anyhow::Result<String> {
    let dt = summary.dt;
    let mut r = MissionReport {
        mission,
        summary,
        offline: None,
        from: 0,
        md: String::new(),
    };
    r.intro(command, grid)?;
    if let Some(offline) = offline {
        // Every team over the same steps: from the first where all have data (the boats'
        // first sample), never a team without data.
        (r.offline, r.from) = (Some(offline), offline.scored_from.min(summary.mse.len()));
        r.error_table(offline)?;
        r.network_equals_offline(offline, events)?;
        r.mse_plot(offline, dir)?;
    }
    r.holdout()?;
    r.innovations()?;
    r.skill()?;
    r.sensor_health()?;
    r.traffic()?;
    r.fleet()?;
    r.eigenvalues(dt)?;
    std::fs::write(dir.join("report.md"), &r.md)?;
    Ok(r.md)
}

/// What the vehicles sensed: the truth (mixed reality), or instruments in the field.
fn truth_of(mission: &fleet_mission::config::MissionConfig) -> String {
    let Some(truth) = &mission.truth else {
        return "there is no truth: the vehicles read their instruments ([sensors]), and the run is scored by the \
            boats' held-out readings"
            .into();
    };
    let what = match &truth.source {
        TruthSource::Preset(p) => format!(
            "the {p:?} plasma cloud at {} x {}, {} frames, averaged by {}",
            truth.sim_grid()[0],
            truth.sim_grid()[1],
            truth.frames,
            truth.average
        ),
        TruthSource::Dataset(d) => format!("the dataset {}", d.display()),
        TruthSource::NetCdf { path, variable, select } => format!(
            "the variable {variable} of {}{}",
            path.display(),
            select.iter().map(|(d, v)| format!(", {d} = {v}")).collect::<String>()
        ),
    };
    format!("the truth is {what} (mixed reality)")
}

impl MissionReport<'_> {
    /// The heading: what ran, on which truth, and the team's settings.
    fn intro(&mut self, command: &str, grid: &fleet_math::grid::Grid) -> anyhow::Result<()> {
        use std::fmt::Write as _;
        let (mission, summary, md) = (self.mission, self.summary, &mut self.md);
        let t = &mission.team;
        writeln!(md, "# Mission `{}`\n", summary.mission)?;
        writeln!(
            md,
            "Command: `{command}`. The model server and {} vehicles ({} aerials, {} boats, radius {}) ran as separate \
                processes over Zenoh; {}.\n",
            summary.vehicles.len(),
            t.aerials,
            t.boats,
            t.radius,
            truth_of(mission)
        )?;
        writeln!(md, "The site's {}.\n", mission.site_said(grid))?;
        let steps = summary.mse.len();
        let time = crate::export::RunTime::of(mission, steps, summary.dt);
        if let (Some(first), Some(last)) = (time.date_of(0), time.date_of(steps.saturating_sub(1))) {
            writeln!(
                md,
                "Time: step 0 is {first} and step {} is {last}, in the `{}` calendar{}.\n",
                steps.saturating_sub(1),
                time.calendar,
                match mission.clock() {
                    Some(_) => " (UTC, the mission's clock)",
                    None => " (the truth file's own dates)",
                }
            )?;
        }
        let placement = match t.placement {
            fleet_mission::team::Placement::Horizon => format!("horizon over {} epochs", t.horizon_epochs),
            p => p.to_string(),
        };
        writeln!(
            md,
            "The team: aerial frames {}, of {}; boat samples {}; fusion `{}`; boats placed by `{placement}`; the model \
                ({} DMD, learning from the `{}` estimate) refitted every boat epoch.\n",
            every(t.aerial_period, "step"),
            if t.aerial_stride == 1 {
                "every cell".to_string()
            } else {
                format!("every {} cell", ordinal(t.aerial_stride))
            },
            every(t.boat_period, "step"),
            t.fusion,
            t.method,
            t.learn_from
        )?;
        Ok(())
    }

    /// The error of every team over the scored steps, and where the fused estimate wins.
    fn error_table(&mut self, offline: &crate::experiment::team::TeamOutcome) -> anyhow::Result<()> {
        use std::fmt::Write as _;
        let (summary, from, md) = (self.summary, self.from, &mut self.md);
        let network_mean = mean_from(&summary.mse, from);
        writeln!(md, "## Estimation error\n")?;
        writeln!(
            md,
            "Mean squared error over the cells with a truth, averaged over steps {from}-{} (from the first step where every team has \
                data: the boats' first sample), and, labelled, from step 0 for the teams that have data there. \
             One run of one seed: for which team is better, with 95% intervals over seeds, see `fleet experiment`.\n",
            summary.mse.len().saturating_sub(1)
        )?;
        if summary.land_cells > 0 {
            writeln!(
                md,
                "The truth has no value at {} cells in any frame (land): they are off the model grid, never in a \
                 boat's disk, and not scored; a cell without a value in one frame (cloud) is not scored then.\n",
                summary.land_cells
            )?;
        }
        let empty: Vec<usize> = (0..summary.mse.len()).filter(|&k| summary.mse[k].is_nan()).collect();
        if !empty.is_empty() {
            let time = crate::export::RunTime::of(self.mission, summary.mse.len(), summary.dt);
            let dates: Vec<String> = empty.iter().take(10).filter_map(|&k| time.date_of(k)).collect();
            writeln!(
                md,
                "The truth has no value at any cell at {} steps ({empty:?}{}): frames without observations, not scored.\n",
                empty.len(),
                if dates.is_empty() { String::new() } else { format!(", dated {}", dates.join(", ")) }
            )?;
        }
        if let Some(u) = self.mission.truth.as_ref().and_then(|t| t.source.units()) {
            writeln!(md, "Values in {u}, as the truth's file says; MSE in ({u})².\n")?;
        }
        writeln!(md, "| team | MSE, steps {from}- | MSE from step 0 |\n|---|---|---|")?;
        writeln!(
            md,
            "| heterogeneous, over the network | {:.4e} | {:.4e} |",
            network_mean,
            mean_from(&summary.mse, 0)
        )?;
        writeln!(
            md,
            "| heterogeneous, offline loop (same truth and seed) | {:.4e} | {:.4e} |",
            offline.mean_heterogeneous, offline.heterogeneous_from_step0
        )?;
        writeln!(
            md,
            "| aerials only | {:.4e} | {:.4e} |",
            offline.mean_aerial_only, offline.aerial_only_from_step0
        )?;
        writeln!(
            md,
            "| boats only | {:.4e} | (no data before step {from}) |\n",
            offline.mean_boat_only
        )?;
        // Where each team is lower, step by step: the fused map against the better single team.
        let steps: Vec<usize> = (from..summary.mse.len().min(offline.aerial_only.len()))
            .filter(|&k| !summary.mse[k].is_nan())
            .collect();
        let wins = steps
            .iter()
            .filter(|&&k| offline.boat_only[k].is_some_and(|b| summary.mse[k] <= b.min(offline.aerial_only[k])))
            .count();
        writeln!(
            md,
            "At {wins} of the {} scored steps the networked heterogeneous estimate is at or below the better of \
            the two single-kind teams.\n",
            steps.len()
        )?;
        Ok(())
    }

    /// Whether the networked run equals the offline loop, and what differed if not.
    fn network_equals_offline(
        &mut self,
        offline: &crate::experiment::team::TeamOutcome,
        events: &[ServerEvent],
    ) -> anyhow::Result<()> {
        use std::fmt::Write as _;
        let (summary, md) = (self.summary, &mut self.md);
        let instruments: Vec<String> = self
            .mission
            .vehicles()
            .iter()
            .map(|v| (v.id.to_string(), self.mission.sensor_of(&v.id)))
            .filter(|(_, s)| *s != fleet_mission::instrument::SensorSource::Sim)
            .map(|(id, s)| format!("{id} ({s})"))
            .collect();
        let max_diff = summary
            .mse
            .iter()
            .zip(&offline.heterogeneous)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        // Equal up to rounding: faer's kernels may round differently in another process (memory
        // alignment picks the vector code path), so bit-for-bit is not promised.
        let same = summary.mse.len() == offline.heterogeneous.len()
            && max_diff <= 1e-9 * offline.mean_heterogeneous.abs().max(f64::MIN_POSITIVE);
        writeln!(
            md,
            "Network equals offline: **{}** (largest per-step difference {max_diff:.1e}).\n",
            if same { "yes, to 1e-9 relative" } else { "no" }
        )?;
        if !same {
            writeln!(md, "{}", differences(events, &summary.counters))?;
        }
        if !instruments.is_empty() {
            writeln!(
                md,
                "Read from instruments, not from the simulated sensors the offline loop draws: {}. Their noise draws \
                    and the places they read differ from the offline loop's, so the two are not expected to be equal.\n",
                instruments.join(", ")
            )?;
        }
        writeln!(md, "![MSE per step](mse.png)\n")?;
        writeln!(
            md,
            "The run's files, beside this report: `estimate.nc` (the fused estimate, its variance and the truth per step, \
                NetCDF; `fleet export` writes it again), `readings.nc` (every boat reading the server accepted, with \
                its sigma and health flag: a CF trajectory file), `recording.mcap` (the Zenoh traffic the server saw and sent and \
                its operations, MCAP: Foxglove reads it, `fleet replay` replays it), `events.jsonl`, `summary.json`, \
                `model.cbor` and `logs/`.\n"
        )?;
        Ok(())
    }

    /// The boats' held-out readings against the estimate, when some were held out.
    fn holdout(&mut self) -> anyhow::Result<()> {
        use std::fmt::Write as _;
        let Some(h) = self.summary.holdout.clone() else {
            return Ok(());
        };
        let share = self.mission.holdout_share();
        writeln!(self.md, "## Held-out readings\n")?;
        writeln!(
            self.md,
            "{:.0}% of the boats' readings (a fixed hash of step and cell) were held out of the fusion and predicted by \
                the estimate of their step, which never saw them.\n",
            share * 100.0
        )?;
        writeln!(self.md, "| | |\n|---|---|")?;
        writeln!(self.md, "| readings held out | {} |", h.readings)?;
        writeln!(self.md, "| mean squared difference | {:.4e} |", h.mse)?;
        writeln!(self.md, "| the readings' own noise variance | {:.4e} |", h.noise_var)?;
        writeln!(
            self.md,
            "| the estimate's MSE there (difference less noise) | {:.4e} |",
            (h.mse - h.noise_var).max(0.0)
        )?;
        writeln!(
            self.md,
            "| inside the estimate's 95% interval | {:.1}% |",
            h.coverage_95 * 100.0
        )?;
        writeln!(
            self.md,
            "| normalised squared error (1: calibrated) | {:.2} |\n",
            h.normalised
        )?;
        self.holdout_deciles(&h)
    }

    /// The held-out readings by decile of the variance the estimate reported at their cells:
    /// whether it is right where it is small and where it is large, without a truth.
    fn holdout_deciles(&mut self, h: &fleet_mission::protocol::HoldoutScore) -> anyhow::Result<()> {
        use std::fmt::Write as _;
        if h.by_decile.is_empty() {
            return Ok(());
        }
        writeln!(
            self.md,
            "By decile of the variance the estimate reported at the readings' cells (smallest first): the mean squared \
                z-score, (reading - estimate)^2 / (reported variance + the reading's noise), is 1 where the reported \
                variance is right, above 1 where it is too small. ENCE (the mean over the deciles of |RMV - RMSE| / \
                RMV): **{:.3}** (0: right in every decile).\n",
            h.ence.unwrap_or(f64::NAN)
        )?;
        writeln!(
            self.md,
            "| decile | readings | mean reported variance | the estimate's error there (difference less noise) | mean z^2 |\n\
             |---|---|---|---|---|"
        )?;
        for (d, dec) in h.by_decile.iter().enumerate() {
            writeln!(
                self.md,
                "| {} | {} | {:.3e} | {:.3e} | {:.2} |",
                d + 1,
                dec.readings,
                dec.variance,
                dec.error,
                dec.z2
            )?;
        }
        writeln!(self.md)?;
        Ok(())
    }

    /// The boats' innovations against the forecast, per epoch: the filter's check of its own
    /// reported variance, without a truth.
    fn innovations(&mut self) -> anyhow::Result<()> {
        use std::fmt::Write as _;
        let steps = &self.summary.innovations;
        if steps.is_empty() {
            return Ok(());
        }
        let (n, nis): (usize, f64) = steps
            .iter()
            .fold((0, 0.0), |(n, s), i| (n + i.values, s + i.nis * i.values as f64));
        writeln!(
            self.md,
            "## Innovations
"
        )?;
        writeln!(
            self.md,
            "The boats' values against the forecast before they were fused, each squared and divided by what the filter \
                expected there (its variance plus the value's noise): 1 when the reported variance is right, above 1 \
                overconfident. Over the mission: **{:.2}** ({n} values).\n",
            nis / n.max(1) as f64
        )?;
        writeln!(
            self.md,
            "| epoch | step | values | normalised innovation squared |\n|---|---|---|---|"
        )?;
        for i in steps {
            writeln!(self.md, "| {} | {} | {} | {:.2} |", i.epoch, i.step, i.values, i.nis)?;
        }
        writeln!(self.md)?;
        Ok(())
    }

    /// The model's skill by epoch: what the filter measured of its forecast, and how far the
    /// map between the aerials' lattice follows it (it falls back to the aerials' own estimate
    /// where the boats have not seen the filter beat it).
    fn skill(&mut self) -> anyhow::Result<()> {
        use std::fmt::Write as _;
        let epochs = &self.summary.skill;
        if epochs.is_empty() {
            return Ok(());
        }
        writeln!(
            self.md,
            "## Forecast skill\n\n\
             Forecast: the model's forecast against the aerials' lattice over the epoch, 1 - (its mean squared error \
             there, less the aerials' noise) / (the lattice values' variance): 1 perfect, 0 no better than the field's \
             mean, below 0 worse. Between: how far the fused map between the lattice follows the filter rather than \
             the aerials' interpolation, as the boats have measured it (0: the aerials' own estimate, 1: the filter's).\n"
        )?;
        writeln!(self.md, "| epoch | forecast | between |\n|---|---|---|")?;
        for s in epochs {
            let forecast = s.forecast.map_or("-".into(), |f| format!("{f:.3}"));
            writeln!(self.md, "| {} | {forecast} | {:.2} |", s.epoch, s.between)?;
        }
        writeln!(self.md)?;
        Ok(())
    }

    /// What the health tests did: every change of a sensor's verdict, and the readings refused,
    /// down-weighted and withheld.
    fn sensor_health(&mut self) -> anyhow::Result<()> {
        use std::fmt::Write as _;
        let (c, verdicts) = (&self.summary.screened, &self.summary.sensor_verdicts);
        if c.checks == 0 {
            return Ok(());
        }
        writeln!(
            self.md,
            "## Sensor health\n\n{} sensor-steps tested: {} value(s) refused as spikes, {} down-weighted, {} withheld \
             (an excluded sensor's), {} aerial frame(s) and {} quadrant(s) refused.\n",
            c.checks, c.spikes_refused, c.down_weighted, c.withheld, c.frames_refused, c.quadrants_refused
        )?;
        let empty: Vec<String> = (self.summary.readings.iter())
            .filter(|(_, r)| r.empty_frames > 0)
            .map(|(v, r)| format!("{v} {}", r.empty_frames))
            .collect();
        if !empty.is_empty() {
            writeln!(
                self.md,
                "Frames with no value at any cell (no-data throughout, or off the site): {}. Frames without \
                 observations: nothing was assimilated from them.\n",
                empty.join(", ")
            )?;
        }
        if verdicts.is_empty() {
            writeln!(self.md, "Every sensor stayed `ok`.\n")?;
            return Ok(());
        }
        writeln!(self.md, "| step | vehicle | from | to | why |\n|---|---|---|---|---|")?;
        for v in verdicts {
            writeln!(
                self.md,
                "| {} | {} | {} | {} | {} |",
                v.step, v.vehicle, v.from, v.to, v.reason
            )?;
        }
        writeln!(self.md)?;
        Ok(())
    }

    /// Each vehicle's link traffic per epoch it took part in, by key and direction (payload
    /// bytes: what the radio must carry of the mission, before Zenoh's and TCP/IP's headers).
    fn traffic(&mut self) -> anyhow::Result<()> {
        use std::fmt::Write as _;
        if self.summary.traffic.is_empty() {
            return Ok(());
        }
        let schedule = self.mission.schedule(self.mission.frames_hint());
        let roster = self.mission.roster();
        writeln!(self.md, "## Link traffic\n")?;
        writeln!(
            self.md,
            "Payload bytes per epoch each vehicle took part in, as its last telemetry before the end said (Zenoh's \
                and TCP/IP's headers and keep-alives are on top; the radio test measures them on the link). Forwarded \
                MAVLink goes per second of the mission, not per epoch: on a real radio, with longer epochs, it is \
                larger per epoch than here.\n"
        )?;
        writeln!(self.md, "| vehicle | out | in | total per epoch |\n|---|---|---|---|")?;
        for (id, t) in &self.summary.traffic {
            let Some(v) = roster.get(id) else { continue };
            let epochs = (0..schedule.epochs())
                .filter(|&e| schedule.seq_of(v.kind, e).is_some())
                .count();
            let per = |bytes: u64| bytes as f64 / epochs.max(1) as f64;
            let side = |m: &std::collections::BTreeMap<String, [u64; 2]>| {
                m.iter()
                    .map(|(k, c)| format!("{k} {}", bytes_text(per(c[1]))))
                    .collect::<Vec<_>>()
                    .join(", ")
            };
            writeln!(
                self.md,
                "| {id} | {} | {} | {} |",
                side(&t.sent),
                side(&t.received),
                bytes_text(per(t.bytes()))
            )?;
        }
        writeln!(self.md)?;
        Ok(())
    }

    /// The fleet's counters and latencies.
    fn fleet(&mut self) -> anyhow::Result<()> {
        use std::fmt::Write as _;
        let (summary, md) = (self.summary, &mut self.md);
        writeln!(md, "## Fleet\n")?;
        let c = &summary.counters;
        let rejected: u64 = c.rejected.values().sum();
        writeln!(md, "| | |\n|---|---|")?;
        writeln!(
            md,
            "| epochs assimilated | {} (model version {}, rank {}) |",
            summary.epochs, summary.model_version, summary.rank
        )?;
        writeln!(
            md,
            "| batches received | {} ({} duplicates, {rejected} refused{}) |",
            c.batches,
            c.duplicates,
            refusals_text(&c.rejected)
        )?;
        writeln!(
            md,
            "| last batch of an epoch to model published | p50 {:.1} ms, p99 {:.1} ms, max {:.1} ms ({} epochs) |",
            summary.latency_ms.p50, summary.latency_ms.p99, summary.latency_ms.max, summary.latency_ms.count
        )?;
        writeln!(
            md,
            "| liveliness tokens seen (link ups) | {} |",
            summary
                .link_ups
                .iter()
                .map(|(k, v)| format!("{k} {v}"))
                .collect::<Vec<_>>()
                .join(", ")
        )?;
        if let Some(mib) = summary.peak_resident_mib {
            writeln!(md, "| server peak resident memory | {mib:.0} MiB |")?;
        }
        writeln!(md, "| server wall time | {:.2} s |\n", summary.wall_s)?;
        Ok(())
    }

    /// The final model's continuous-time eigenvalues.
    fn eigenvalues(&mut self, dt: f64) -> anyhow::Result<()> {
        use std::fmt::Write as _;
        let (summary, md) = (self.summary, &mut self.md);
        writeln!(md, "## Final model: continuous-time eigenvalues ln(lambda)/dt\n")?;
        writeln!(md, "| # | growth rate | frequency (rad/s) |\n|---|---|---|")?;
        for (j, l) in summary.eigenvalues.iter().enumerate() {
            let z = num_complex::Complex64::new(l[0], l[1]).ln() / dt;
            writeln!(md, "| {} | {:.4} | {:.4} |", j + 1, z.re, z.im)?;
        }
        Ok(())
    }

    /// `mse.png`: every team's error per step from the first step every team has data at.
    fn mse_plot(&self, offline: &crate::experiment::team::TeamOutcome, dir: &std::path::Path) -> anyhow::Result<()> {
        use crate::plot::{self, Series};
        let (summary, from) = (self.summary, self.from);
        // Every curve from the first step every team has data at.
        let series = |name: &str, v: &[Option<f64>]| Series {
            name: name.into(),
            points: v
                .iter()
                .enumerate()
                .skip(from)
                .filter_map(|(k, e)| e.map(|e| (k as f64, e)))
                .collect(),
        };
        let some = fleet_math::fusion::scored;
        plot::lines(
            dir.join("mse.png"),
            &format!(
                "Mission {}: estimation error per step, from step {from} (every team has data)",
                summary.mission
            ),
            "step",
            "MSE",
            &[
                series("heterogeneous (network)", &some(&summary.mse)),
                series("aerials only", &some(&offline.aerial_only)),
                series("boats only", &offline.boat_only),
            ],
            true,
        )?;
        Ok(())
    }
}

/// The refusals by reason, as a reader would want them: "" when there were none, else
/// ": reason n, reason m" (the map printed raw showed `{}` to a field team).
fn refusals_text(rejected: &std::collections::BTreeMap<String, u64>) -> String {
    if rejected.is_empty() {
        return String::new();
    }
    let by_reason: Vec<String> = rejected.iter().map(|(reason, n)| format!("{reason} {n}")).collect();
    format!(": {}", by_reason.join(", "))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rates_read_as_english() {
        assert_eq!(
            (every(1, "step"), every(5, "step")),
            ("every step".to_string(), "every 5 steps".to_string())
        );
        let got: Vec<String> = [1, 2, 3, 4, 5, 11, 12, 13, 21, 22, 23, 101, 111]
            .iter()
            .map(|&n| ordinal(n))
            .collect();
        assert_eq!(
            got,
            ["1st", "2nd", "3rd", "4th", "5th", "11th", "12th", "13th", "21st", "22nd", "23rd", "101st", "111th"]
        );
    }

    #[test]
    fn refusals_read_as_english() {
        let mut rejected = std::collections::BTreeMap::new();
        assert_eq!(refusals_text(&rejected), "");
        rejected.insert("bad signature".to_string(), 2);
        rejected.insert("stale".to_string(), 1);
        assert_eq!(refusals_text(&rejected), ": bad signature 2, stale 1");
    }
}
