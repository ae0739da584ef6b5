//! A request's spec made ready (all three sample calls): validated, resolved to its dataset and
//! generator, admitted by size, and the job that makes, crops and encodes its samples.

use std::sync::Arc;

use super::state::State;
use crate::sample::error::SampleError;
use crate::sample::pipeline::Generator;
use crate::service::dataset::Dataset;
use crate::service::encode::{to_proto, OutputSpec};
use crate::service::error::{panic_message, ServiceError};
use crate::service::pb;
use crate::service::pool::{Make, Prepare, Produce};
use crate::service::spec::{self, Spec};
use crate::service::{validate, work};

/// A request's spec made ready: the job that makes its samples, and what the log says of it.
pub(super) struct Prepared {
    pub(super) dataset: String,
    pub(super) fingerprint: u64,
    pub(super) seed: u64,
    pub(super) produce: Produce,
}

impl State {
    /// The job of a stream: make the sample, crop it, encode it (on a worker).
    fn produce(&self, dataset: Arc<Dataset>, generator: Arc<Generator>, seed: u64, out: OutputSpec) -> Produce {
        let metrics = self.metrics.clone();
        let prepare: Option<Prepare> = self.config.prefetch_scenes.then(|| {
            let g = generator.clone();
            Arc::new(move |index: u64, done: Box<dyn FnOnce() + Send>| g.prepare(index, done)) as Prepare
        });
        let make: Make = Arc::new(move |index| {
            // a plain crop is made over its window only; an augmentation crops what it resizes
            let crop = out.crop.filter(|_| out.augment.is_none());
            let made = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| match &crop {
                Some(c) => generator.sample_cropped(seed, index, c),
                None => generator.sample(seed, index).map(|s| (s, (0, 0))),
            }))
            .map_err(|payload| {
                let item = generator.source_item(index).map_or_else(|| "none".to_string(), |i| dataset.source.id(i));
                let e = ServiceError::Panicked {
                    dataset: dataset.name.clone(),
                    index,
                    item,
                    message: panic_message(payload.as_ref()),
                };
                tracing::error!(error = %e, "sample failed");
                e
            })?;
            let (s, mut corner) = made.map_err(|source| {
                if let SampleError::Crop(e) = &source {
                    // a crop larger than the frame is the request's fault, never shrunk
                    return ServiceError::invalid("crop", e.to_string());
                }
                metrics.observe_error(&source);
                tracing::warn!(dataset = %dataset.name, index, error = %source, "sample failed");
                ServiceError::Generation { index, source }
            })?;
            if s.skipped_sources > 0 {
                let opened = dataset.opened_skips();
                let mut counts = generator.skip_counts();
                for (k, n) in opened {
                    *counts.entry(k).or_default() += n;
                }
                if metrics.record_skips(&dataset.name, &counts) {
                    for (item, id, reason) in generator.skipped() {
                        tracing::warn!(dataset = %dataset.name, item, id = %id, reason = %reason, "bad source passed over");
                    }
                }
            }
            let timings = s.timings;
            let mut record = String::new();
            let s = match &out.augment {
                Some(a) => {
                    // the augmentation makes its own crop (the frame resized to fit it)
                    let (s, r) = a.apply(s);
                    record = r.to_json();
                    corner = (0, 0);
                    s
                }
                None => s,
            };
            let mut p = to_proto(s, &dataset.name, corner, &out);
            p.augment = record;
            metrics.observe_sample(&timings, p.timings.as_ref().map_or(0.0, |t| t.encode_ms));
            Ok(p)
        });
        Produce { make, prepare, bound: 0, work: 0, workspace: 0 }
    }

    /// The one path of a request's spec (all three calls): validated into a [`Spec`], resolved
    /// to the dataset and the generator of its overrides, the fingerprint checked, the outputs
    /// checked against the motion law, and admitted by size; then the job that makes its samples.
    pub(super) fn prepare(&self, spec: Option<&pb::SampleSpec>) -> Result<Prepared, ServiceError> {
        let spec = Spec::try_from((&*spec::of(spec), &self.config))?;
        let ds = self.datasets.get(&spec.dataset)?;
        let generator = ds.generator(&spec.overrides)?;
        if spec.fingerprint != 0 && spec.fingerprint != generator.fingerprint() {
            return Err(ServiceError::FingerprintMismatch {
                dataset: ds.name.clone(),
                requested: spec.fingerprint,
                actual: generator.fingerprint(),
            });
        }
        validate::outputs_fit_motion(&spec.out, generator.config())?;
        let bound = validate::admit_size(&spec.out, spec.frames(), &self.config, self.scheduler.budget())?;
        let work = work::admit(&spec.out, spec.frames(), generator.config().resample, &self.config)?;
        let (dataset, fingerprint, seed) = (ds.name.clone(), generator.fingerprint(), spec.seed);
        let mut produce = self.produce(ds, generator, seed, spec.out);
        produce.bound = bound;
        produce.work = work;
        Ok(Prepared { dataset, fingerprint, seed, produce })
    }
}
