//! A run of a bake over the items of one shard: each item loaded, its scene built and written,
//! the failures and timings gathered into the report.

use std::time::Instant;

use super::baker::Baker;
use super::tars::TarOut;
use super::types::{
    io_err, peak_rss_mib, BakeError, BakeFailure, BakeLayout, BakeReport, BakeTimings, Progress, Shard,
};
use crate::io::image::quantize_to_u8;
use crate::scene::SceneError;
use crate::source::FailureKind;

impl Baker {
    /// Bakes the not yet baked items of `shard`, at most `limit` of them (then stops, as an
    /// interrupted run would), calling `progress` after each item. Items that fail are passed
    /// over and reported; an error of ONNX Runtime itself or of the output folder stops the run.
    pub fn run(
        &self,
        shard: &Shard,
        limit: Option<usize>,
        mut progress: impl FnMut(Progress),
    ) -> Result<BakeReport, BakeError> {
        let start = Instant::now();
        let partial = self.partial_dir(shard);
        std::fs::create_dir_all(self.out.join(".partial")).map_err(|e| io_err(&partial, e))?;
        // a WebDataset bake first keeps what a killed run of this shard finished
        let mut tars = match self.layout {
            BakeLayout::WebDataset { items_per_shard } => Some(self.open_tars(shard, items_per_shard)?),
            BakeLayout::Reference => None,
        };
        // leftovers of a killed run of this shard (never another shard's)
        if partial.exists() {
            std::fs::remove_dir_all(&partial).map_err(|e| io_err(&partial, e))?;
        }
        std::fs::create_dir_all(&partial).map_err(|e| io_err(&partial, e))?;
        let runs_before: Vec<(&str, u64)> = self.stage.model_runs();
        let items = self.items(shard);
        let mut p = Progress { handled: 0, total: items.len(), baked: 0, failed: 0 };
        let mut tally = Tally::default();
        for &i in &items {
            if limit.is_some_and(|l| p.baked + p.failed >= l) {
                break;
            }
            p.handled += 1;
            match self.bake_item(shard, i, tars.as_mut(), &mut tally)? {
                Outcome::Done => {}
                Outcome::Failed => p.failed += 1,
                Outcome::Baked => p.baked += 1,
            }
            progress(p);
        }
        if let Some(open) = tars.and_then(|t| t.open) {
            open.finish()?;
        }
        std::fs::remove_dir_all(&partial).ok();
        Ok(self.report(shard, start, p, items.len(), tally, &runs_before))
    }

    /// Bakes item `i` unless it is done: a failure of the item is recorded in `tally`, an error
    /// of ONNX Runtime itself or of the output folder returned.
    fn bake_item(
        &self,
        shard: &Shard,
        i: usize,
        tars: Option<&mut TarOut>,
        tally: &mut Tally,
    ) -> Result<Outcome, BakeError> {
        let id = self.source.id(i);
        let name = self.names[i].clone();
        let done = match (&tars, &name) {
            (_, Err(_)) => false,
            (Some(t), Ok(n)) => t.done.contains(n),
            (None, Ok(n)) => self.is_done(n),
        };
        if done {
            tally.already_done += 1;
            return Ok(Outcome::Done);
        }
        let fail = |kind: &str, reason: String| BakeFailure { item: i, id: id.clone(), kind: kind.into(), reason };
        let name = match name {
            Ok(n) => n,
            Err(reason) => {
                tally.failures.push(fail(FailureKind::Decode.as_str(), reason));
                return Ok(Outcome::Failed);
            }
        };
        let t = Instant::now();
        let loaded = self.source.load(i).map_err(SceneError::from).and_then(|mut item| {
            // the models see exactly the image that is stored (and served)
            quantize_to_u8(&mut item.image);
            // the built-in MPI is not stored, so it is not built
            self.stage.parts(item, self.manifest.has("mpis"))
        });
        let scene = match loaded {
            Ok(mut s) => {
                s.id = name;
                s
            }
            Err(e @ SceneError::Runtime(_)) => return Err(BakeError::Runtime(e)),
            Err(e) => {
                let kind = e.failure_kind().map_or("model", FailureKind::as_str);
                tally.failures.push(fail(kind, crate::failure::printable(&e.to_string(), 1000)));
                return Ok(Outcome::Failed);
            }
        };
        tally.scene_ms.push(t.elapsed().as_secs_f64() * 1e3);
        let t = Instant::now();
        // the output folder failing (full, read-only) stops the run: no item could be written
        self.write_scene(shard, &scene, tars)?;
        tally.write_ms += t.elapsed().as_secs_f64() * 1e3;
        Ok(Outcome::Baked)
    }

    /// The report of a run of `shard` that started at `start` over `shard_items` items.
    fn report(
        &self,
        shard: &Shard,
        start: Instant,
        p: Progress,
        shard_items: usize,
        tally: Tally,
        runs_before: &[(&str, u64)],
    ) -> BakeReport {
        let Tally { already_done, failures, scene_ms, write_ms } = tally;
        let total_s = start.elapsed().as_secs_f64();
        let mut sorted = scene_ms.clone();
        sorted.sort_by(f64::total_cmp);
        let n = scene_ms.len().max(1) as f64;
        let timings = BakeTimings {
            total_s,
            items_per_s: if total_s > 0.0 { p.baked as f64 / total_s } else { 0.0 },
            scene_ms_mean: scene_ms.iter().sum::<f64>() / n,
            scene_ms_median: sorted.get(sorted.len() / 2).copied().unwrap_or(0.0),
            scene_ms_max: sorted.last().copied().unwrap_or(0.0),
            write_ms_mean: write_ms / n,
        };
        let model_runs = self
            .stage
            .model_runs()
            .into_iter()
            .map(|(role, runs)| {
                let before = runs_before.iter().find(|(r, _)| *r == role).map_or(0, |(_, n)| *n);
                (role.to_string(), runs - before)
            })
            .collect();
        BakeReport {
            format: "mpiflow bake report v1".into(),
            shard: shard.to_string(),
            source: self.source.describe(),
            source_items: self.source.len(),
            shard_items,
            baked: p.baked,
            already_done,
            failed: p.failed,
            remaining: shard_items - p.handled,
            failures,
            models: self.manifest.models.clone(),
            model_runs,
            timings,
            peak_rss_mib: peak_rss_mib(),
        }
    }
}

/// What became of one item of a run.
enum Outcome {
    /// Baked by an earlier run.
    Done,
    /// Passed over and reported.
    Failed,
    Baked,
}

/// What a run gathers for its report besides the progress counts.
#[derive(Default)]
struct Tally {
    already_done: usize,
    failures: Vec<BakeFailure>,
    /// Each baked item's load and scene time.
    scene_ms: Vec<f64>,
    /// The write time of all baked items.
    write_ms: f64,
}
