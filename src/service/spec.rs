//! The request spec: `pb::SampleSpec`, the sample options shared by StreamSamples, GetSample and
//! GetSamples, validated once into [`Spec`] (what the domain needs: the dataset word, the seed,
//! the outputs and the configuration overrides); and the three requests built from one spec.

use super::config::ServiceConfig;
use super::dataset::Overrides;
use super::encode::OutputSpec;
use super::error::ServiceError;
use super::pb;
use super::validate;

/// A validated [`pb::SampleSpec`]: every field checked, in the order of the message.
#[derive(Clone, Debug, PartialEq)]
pub struct Spec {
    /// The dataset name (empty = the server's default).
    pub dataset: String,
    /// The fingerprint the client expects (0 = no check).
    pub fingerprint: u64,
    pub seed: u64,
    /// Fields, dtype, compression, crop and augmentation of each sample.
    pub out: OutputSpec,
    /// The changes to the dataset's sample configuration (motion, objects, frames, kernel).
    pub overrides: Overrides,
}

impl Spec {
    /// Frames per sample (2 unless the spec asks for a clip).
    pub fn frames(&self) -> usize {
        self.overrides.frames.unwrap_or(crate::sample::config::MIN_FRAMES)
    }
}

impl TryFrom<(&pb::SampleSpec, &ServiceConfig)> for Spec {
    type Error = ServiceError;

    /// Checks every field of the spec against the server's limits; a refusal is
    /// INVALID_ARGUMENT starting with the field's name.
    fn try_from((s, config): (&pb::SampleSpec, &ServiceConfig)) -> Result<Self, ServiceError> {
        let mut out = validate::output_spec(&s.fields, s.flow_dtype, s.compression, s.crop.as_ref(), config)?;
        validate::augment(&s.augment, &mut out, config)?;
        let mut overrides =
            validate::overrides(&s.motion_preset, &s.motion_ranges_json, s.max_objects, s.motions_per_image)?;
        validate::frames(s.frames, &out, &mut overrides)?;
        overrides.resample = validate::resample(&s.resample)?;
        Ok(Spec { dataset: s.dataset.clone(), fingerprint: s.fingerprint, seed: s.seed, out, overrides })
    }
}

impl pb::SampleSpec {
    /// A StreamSamples request of this spec from index 0, endless (set the stream's own fields
    /// with struct update syntax: `pb::StreamRequest { count: 4, ..spec.stream() }`).
    pub fn stream(self) -> pb::StreamRequest {
        pb::StreamRequest { spec: Some(self), ..Default::default() }
    }

    /// The GetSample request of this spec for `index`.
    pub fn sample(self, index: u64) -> pb::SampleRequest {
        pb::SampleRequest { spec: Some(self), index }
    }

    /// The GetSamples request of this spec for `indices`.
    pub fn samples(self, indices: Vec<u64>) -> pb::SamplesRequest {
        pb::SamplesRequest { spec: Some(self), indices }
    }
}

/// The spec of a request (an unset spec is all defaults).
pub fn of(spec: Option<&pb::SampleSpec>) -> std::borrow::Cow<'_, pb::SampleSpec> {
    spec.map_or_else(|| std::borrow::Cow::Owned(pb::SampleSpec::default()), std::borrow::Cow::Borrowed)
}
