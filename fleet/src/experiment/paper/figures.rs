//! The report's figures: Fig. 10 (MSE over time), Fig. 11 (truth beside the reconstruction,
//! and the reported uncertainty), Fig. 7 (dominant eigenvalue estimates) and Fig. 8
//! (forgetting), each written beside `report.md` and linked from it.

use super::{where_valued, Report, RowResult};
use crate::experiment::eig_study;
use crate::plot::{self, Panel, Series};
use fleet_math::grid::area_average;
use std::fmt::Write as _;

impl Report<'_> {
    /// Fig. 10: per cloud, its first row: the mean over seeds with its 95% band.
    pub(super) fn fig10(&mut self) -> anyhow::Result<()> {
        let Report {
            dir, res, md, figures, ..
        } = self;
        let seeds = res.config.seeds();

        writeln!(
            md,
            "## Fig. 10: MSE over time, mean over seeds with the 95% interval shaded\n"
        )?;
        let mut seen = vec![];
        for r in &res.rows {
            if seen.contains(&r.row.name()) {
                continue;
            }
            seen.push(r.row.name());
            let name = format!("fig10-{}.png", r.row.name()).to_lowercase();
            let bands: Vec<plot::Band> = r
                .curves()
                .into_iter()
                .map(|(team, pts)| plot::Band {
                    name: team,
                    // Every team from the first step where all have data (the scored steps).
                    points: pts
                        .iter()
                        .filter(|(k, _)| *k >= r.scored_from)
                        .map(|(k, i)| {
                            (
                                *k as f64,
                                i.mean,
                                if i.n > 1 { i.lo } else { i.mean },
                                if i.n > 1 { i.hi } else { i.mean },
                            )
                        })
                        .collect(),
                })
                .collect();
            plot::bands(
                dir.join(&name),
                &format!(
                    "{}: MSE at each step from step {} (all teams have data; {} seeds)",
                    r.row.name(),
                    r.scored_from,
                    seeds.len()
                ),
                "step",
                "MSE",
                &bands,
                true,
            )?;
            writeln!(md, "![{name}]({name})\n")?;
            figures.push(name);
        }
        Ok(())
    }

    /// Fig. 11: the most complex cloud's first row, first seed, three boat steps.
    pub(super) fn fig11(&mut self) -> anyhow::Result<()> {
        let res = self.res;
        let Some(r) = res
            .verdict
            .preset
            .as_ref()
            .and_then(|p| res.rows.iter().find(|r| &r.row.name() == p))
        else {
            return Ok(());
        };
        let seeds = res.config.seeds();
        writeln!(
            self.md,
            "## Fig. 11: truth and reconstruction ({}, seed {}), boats' disks in white\n",
            r.row.name(),
            seeds[0]
        )?;
        let truth = &self.truths[&r.row.name()];
        let (rows, cols) = (r.model_grid[0], r.model_grid[1]);
        let steps = &r.figure.boat_steps;
        let picks: Vec<usize> = if steps.len() >= 3 {
            vec![0, steps.len() / 2, steps.len() - 1]
        } else {
            (0..steps.len()).collect()
        };
        let mut owned = vec![];
        for &i in &picks {
            let k = steps[i];
            let col: Vec<f64> = truth.snapshots.col(k).iter().copied().collect();
            owned.push((k, i, area_average(&col, truth.rows, truth.cols, rows, cols)?));
        }
        self.fig11_fields(r, &owned)?;
        self.fig11_uncertainty(r, &owned)
    }

    /// The truth beside the estimate at the picked boat steps, with the boats' disks; where the
    /// truth has no value (land, cloud) every panel is drawn the same, in no-data grey.
    pub(super) fn fig11_fields(&mut self, r: &RowResult, owned: &[(usize, usize, Vec<f64>)]) -> anyhow::Result<()> {
        let (rows, cols) = (r.model_grid[0], r.model_grid[1]);
        let radius = self.res.config.radius / r.row.mv_space as f64;
        let estimates: Vec<Vec<f64>> = owned
            .iter()
            .map(|(_, i, t)| where_valued(&r.figure.snapshots[*i], t))
            .collect();
        let mut panels = vec![];
        for ((k, i, t), estimate) in owned.iter().zip(&estimates) {
            let disks: Vec<(f64, f64, f64)> = r.figure.disks[*i]
                .iter()
                .map(|&(a, b)| (a as f64, b as f64, radius))
                .collect();
            panels.push(Panel {
                values: t,
                rows,
                cols,
                title: format!("truth, step {k}"),
                disks: disks.clone(),
            });
            panels.push(Panel {
                values: estimate,
                rows,
                cols,
                title: format!("heterogeneous estimate, step {k}"),
                disks,
            });
        }
        let range = plot::range_of(&panels[..panels.len().min(1)]);
        plot::png(self.dir.join("fig11.png"), &panels, Some(range))?;
        writeln!(self.md, "![fig11](fig11.png)\n")?;
        self.figures.push("fig11.png".into());
        Ok(())
    }

    /// The uncertainty the estimate reports beside the error it makes, on one scale.
    pub(super) fn fig11_uncertainty(
        &mut self,
        r: &RowResult,
        owned: &[(usize, usize, Vec<f64>)],
    ) -> anyhow::Result<()> {
        let (rows, cols) = (r.model_grid[0], r.model_grid[1]);
        writeln!(
            self.md,
            "Below, at the same steps: the standard deviation the estimate reports at each cell beside its \
            actual error (absolute value), on one colour scale.\n"
        )?;
        let sd: Vec<(usize, Vec<f64>, Vec<f64>)> = owned
            .iter()
            .map(|(k, i, t)| {
                let std: Vec<f64> = r.figure.snapshot_variances[*i]
                    .iter()
                    .map(|v| v.max(0.0).sqrt())
                    .collect();
                let std = where_valued(&std, t);
                let err = r.figure.snapshots[*i]
                    .iter()
                    .zip(t)
                    .map(|(e, x)| (e - x).abs())
                    .collect();
                (*k, std, err)
            })
            .collect();
        let mut panels = vec![];
        for (k, std, err) in &sd {
            panels.push(Panel {
                values: std,
                rows,
                cols,
                title: format!("reported standard deviation, step {k}"),
                disks: vec![],
            });
            panels.push(Panel {
                values: err,
                rows,
                cols,
                title: format!("|error|, step {k}"),
                disks: vec![],
            });
        }
        plot::png(
            self.dir.join("fig11-uncertainty.png"),
            &panels,
            Some(plot::range_of(&panels)),
        )?;
        writeln!(self.md, "![fig11-uncertainty](fig11-uncertainty.png)\n")?;
        self.figures.push("fig11-uncertainty.png".into());
        Ok(())
    }

    /// Fig. 7: the eigenvalue study.
    pub(super) fn eig_study(&mut self) -> anyhow::Result<()> {
        let Report {
            dir, res, md, figures, ..
        } = self;
        if !res.eig_study.is_empty() {
            writeln!(
                md,
                "## Fig. 7: dominant continuous-time eigenvalue (true -1 + 0i), {} trials\n",
                res.config.eig_trials
            )?;
            for (part, idx, reference) in [("real", 0usize, -1.0), ("imaginary", 1, 0.0)] {
                let groups: Vec<(String, Vec<f64>)> = res
                    .eig_study
                    .iter()
                    .map(|b| {
                        (
                            format!("{} {}", b.method, b.noise_var),
                            b.estimates.iter().map(|e| e[idx]).collect(),
                        )
                    })
                    .collect();
                let name = format!("fig7-{part}.png");
                plot::boxes(
                    dir.join(&name),
                    &format!("Dominant eigenvalue, {part} part (method, noise variance)"),
                    part,
                    &groups,
                    Some(reference),
                )?;
                writeln!(md, "![{name}]({name})\n")?;
                figures.push(name);
            }
            writeln!(
                md,
                "| method | noise variance | median real part | median imaginary part |\n|---|---|---|---|"
            )?;
            for b in &res.eig_study {
                let mut re: Vec<f64> = b.estimates.iter().map(|e| e[0]).collect();
                let mut im: Vec<f64> = b.estimates.iter().map(|e| e[1]).collect();
                writeln!(
                    md,
                    "| {} | {} | {:.4} | {:.4} |",
                    b.method,
                    b.noise_var,
                    eig_study::median(&mut re),
                    eig_study::median(&mut im)
                )?;
            }
            writeln!(md)?;
        }
        Ok(())
    }

    /// Fig. 8: the forgetting factor.
    pub(super) fn forgetting(&mut self) -> anyhow::Result<()> {
        let Report {
            dir, res, md, figures, ..
        } = self;
        if !res.forgetting.is_empty() {
            let unit = match res.config.forgetting_unit {
                fleet_math::dmd::ForgettingUnit::Batch => {
                    "per update of 60 pairs (the paper's reading: each update multiplies the past by gamma)"
                }
                fleet_math::dmd::ForgettingUnit::Pair => "per pair (odmd's: each pair weighs gamma^age)",
            };
            writeln!(
                md,
                "## Fig. 8: forgetting factor (eigenvalue-study field, noise variance 0.01), gamma {unit}, along \
                the directions each update excites\n"
            )?;
            let series: Vec<Series> = res
                .forgetting
                .iter()
                .map(|c| Series {
                    name: c.label.clone(),
                    points: c.points.clone(),
                })
                .collect();
            plot::lines(
                dir.join("fig8.png"),
                "Dominant eigenvalue (real part) as pairs arrive; true value -1",
                "pairs assimilated",
                "Re(lambda)",
                &series,
                false,
            )?;
            writeln!(md, "![fig8](fig8.png)\n")?;
            writeln!(
                md,
                "A forgetting factor keeps an effective memory of about `1/(1 - gamma)` updates (per batch) or pairs \
                    (per pair). \
                 With `N = 400` cells, a memory below ~400 pairs fits the operator to fewer pairs than it has unknowns \
                 per row, and its \
                 dominant eigenvalue follows the noise. Set `forgetting_unit = \"pair\"` in the experiment file for \
                     odmd's reading.\n"
            )?;
            figures.push("fig8.png".into());
        }
        Ok(())
    }
}
