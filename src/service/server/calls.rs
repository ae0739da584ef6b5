//! The calls' work on [`State`]: a sample stream opened (StreamSamples, GetSamples), one sample
//! made (GetSample and the warm-up), an upload received, the server described (GetInfo).

use std::sync::atomic::Ordering;
use std::sync::Arc;

use tokio_stream::StreamExt;
use tonic::{Status, Streaming};

use super::admission::{CallKind, CountedStream};
use super::state::State;
use crate::service::error::{from_request_stream, Reason, ServiceError};
use crate::service::pb;
use crate::service::pool::{Client, SampleStream, StreamSpec, END_INDEX};
use crate::service::validate;

impl State {
    pub(super) fn open_stream(
        self: &Arc<Self>,
        r: &pb::StreamRequest,
        client: Client,
    ) -> Result<CountedStream, ServiceError> {
        if self.draining.load(Ordering::SeqCst) {
            return Err(ServiceError::Draining);
        }
        let (rank, world, batch, prefetch) = validate::stream_shape(r, &self.config)?;
        let p = self.prepare(r.spec.as_ref())?;
        // the stream limit
        let admitted = self.admit(CallKind::Stream, client.peer)?;
        let spec = StreamSpec {
            start_index: r.start_index,
            rank: u64::from(rank),
            world_size: u64::from(world),
            count: r.count,
            batch_size: batch as usize,
            prefetch: prefetch as usize,
            max_message_bytes: self.config.max_message_bytes() as usize,
        };
        let peer = client.peer;
        let inner = self.scheduler.open_for(client, spec, p.produce)?;
        self.slot_streams.lock().unwrap_or_else(std::sync::PoisonError::into_inner).insert(inner.id());
        self.metrics.active_streams.inc();
        tracing::info!(
            %peer,
            stream = inner.id(),
            dataset = %p.dataset,
            fingerprint = format!("{:016x}", p.fingerprint),
            seed = p.seed,
            rank,
            world_size = world,
            start_index = r.start_index,
            count = r.count,
            batch,
            prefetch,
            "stream opened"
        );
        Ok(CountedStream { inner, _admitted: admitted })
    }

    /// [`State::open_stream`]; when every slot of `max_streams` is taken, once more after a slot
    /// was taken back from a stream that makes no progress ([`State::reclaim_stream_slot`]).
    pub(super) async fn open_stream_making_room(
        self: &Arc<Self>,
        r: &pb::StreamRequest,
        client: Client,
    ) -> Result<CountedStream, ServiceError> {
        match self.open_stream(r, client.clone()) {
            Err(ServiceError::TooManyStreams { .. }) if self.reclaim_stream_slot(client.peer).await => {
                self.open_stream(r, client)
            }
            opened => opened,
        }
    }

    /// The samples of an explicit index list, in its order (GetSamples): a stream of the pool
    /// with the list as its positions, counted against `max_streams`, one sample per message.
    pub(super) fn open_samples(
        self: &Arc<Self>,
        r: &pb::SamplesRequest,
        client: Client,
    ) -> Result<CountedStream, ServiceError> {
        if self.draining.load(Ordering::SeqCst) {
            return Err(ServiceError::Draining);
        }
        let indices = validate::indices(&r.indices)?;
        let p = self.prepare(r.spec.as_ref())?;
        let admitted = self.admit(CallKind::RandomAccess, client.peer)?;
        // as many made ahead as keep every worker busy (within max_prefetch)
        let prefetch = (self.config.default_prefetch as usize)
            .max(self.scheduler.workers())
            .min(self.config.max_prefetch as usize)
            .min(indices.len());
        let n = indices.len();
        let max_bytes = self.config.max_message_bytes() as usize;
        let inner = self.scheduler.open_indices(client, indices, 1, prefetch, max_bytes, p.produce)?;
        self.metrics.active_streams.inc();
        tracing::debug!(
            stream = inner.id(),
            dataset = %p.dataset,
            fingerprint = format!("{:016x}", p.fingerprint),
            seed = p.seed,
            indices = n,
            prefetch,
            "samples opened"
        );
        Ok(CountedStream { inner, _admitted: admitted })
    }

    /// One sample through the worker pool (GetSample and the warm-up), with its place in the
    /// byte budget: the sample's bytes stay counted until the returned stream is dropped (with
    /// the reply, once sent: [`ReplyHold`](crate::service::reply::ReplyHold)).
    pub async fn one_sample(
        self: &Arc<Self>,
        r: &pb::SampleRequest,
        client: Client,
    ) -> Result<(pb::Sample, SampleStream), Status> {
        if r.index == END_INDEX {
            return Err(ServiceError::invalid("index", "2^64 - 1 is the end of the index space, not a sample").into());
        }
        let p = self.prepare(r.spec.as_ref())?;
        let spec = StreamSpec {
            start_index: r.index,
            rank: 0,
            world_size: 1,
            count: 1,
            batch_size: 1,
            prefetch: 1,
            max_message_bytes: self.config.max_message_bytes() as usize,
        };
        let mut stream = self.scheduler.open_for(client, spec, p.produce)?;
        match stream.next().await {
            Some(Ok(mut b)) if !b.samples.is_empty() => Ok((b.samples.swap_remove(0), stream)),
            // the status without the stream's cursor, with its reason
            Some(Err(status)) => {
                let mut s = Status::new(status.code(), status.message().to_string());
                if let Some(r) = Reason::of(&status) {
                    r.set(&mut s);
                }
                Err(s)
            }
            _ => Err(ServiceError::Internal("no sample came back".into()).into()),
        }
    }

    /// Receives an upload's chunks into a session of the upload store, commits it, and (re)makes
    /// the uploaded dataset. Nothing of a failed upload is kept.
    pub(super) async fn upload(
        &self,
        mut chunks: Streaming<pb::SourceChunk>,
    ) -> Result<pb::UploadSummary, ServiceError> {
        if self.draining.load(Ordering::SeqCst) {
            return Err(ServiceError::Draining);
        }
        // the in-progress budgets: a slot now, bytes as they arrive (RESOURCE_EXHAUSTED over them)
        let mut session = self.datasets.uploads.session()?;
        let mut dataset = String::new();
        while let Some(chunk) = chunks.message().await.map_err(from_request_stream)? {
            if dataset.is_empty() {
                dataset = chunk.dataset.clone();
                if self.datasets.is_configured(&dataset) {
                    return Err(ServiceError::invalid(
                        "dataset",
                        format!("{dataset} is a configured dataset; upload to another name"),
                    ));
                }
            }
            session.push(&dataset, &chunk.name, &chunk.kind, &chunk.data)?;
        }
        // a new dataset of photos alone, with no depth model: nothing of it could make a scene
        let fresh = !dataset.is_empty() && self.datasets.get(&dataset).is_err();
        if fresh && self.datasets.stage.depth.is_none() && !session.has_depth() {
            return Err(ServiceError::Unusable { dataset, source: crate::scene::SceneError::NoDepthModel });
        }
        let datasets = self.datasets.clone();
        let summary = tokio::task::spawn_blocking(move || -> Result<_, ServiceError> {
            let summary = session.finish()?;
            if summary.sources > 0 {
                datasets.refresh_upload(&summary)?;
            }
            Ok(summary)
        })
        .await
        .map_err(|e| ServiceError::Internal(format!("upload: {e}")))??;
        tracing::info!(dataset = %summary.dataset, accepted = summary.accepted, rejected = summary.rejected.len(), sources = summary.sources, "upload");
        let fingerprint = self.datasets.get(&summary.dataset).map(|d| d.fingerprint()).unwrap_or(summary.fingerprint);
        Ok(pb::UploadSummary {
            dataset: summary.dataset,
            accepted: summary.accepted,
            rejected: summary.rejected,
            fingerprint,
            sources: summary.sources,
        })
    }

    pub(super) fn info(&self) -> pb::InfoResponse {
        let stage = &self.datasets.stage;
        let mut models = vec![pb::ModelInfo { role: "mpi".into(), name: stage.mpi.name() }];
        if let Some(d) = &stage.depth {
            models.push(pb::ModelInfo { role: "depth".into(), name: d.name() });
        }
        if let Some(s) = &stage.segmenter {
            models.push(pb::ModelInfo { role: "segment".into(), name: s.name() });
        }
        let c = &self.config;
        pb::InfoResponse {
            version: env!("CARGO_PKG_VERSION").into(),
            datasets: self
                .datasets
                .all()
                .iter()
                .enumerate()
                .map(|(i, d)| pb::DatasetInfo {
                    name: d.name.clone(),
                    fingerprint: d.fingerprint(),
                    sources: d.sources() as u64,
                    description: d.description.clone(),
                    is_default: i == 0,
                    skipped: self.metrics.skipped_of(&d.name),
                    needs_models: d.loader.needs_models(),
                    baked_with: d.source.baked_with().unwrap_or_default(),
                })
                .collect(),
            models,
            limits: Some(pb::Limits {
                max_message_bytes: c.max_message_bytes(),
                max_streams: c.max_streams as u32,
                max_batch_size: c.max_batch_size,
                max_prefetch: c.max_prefetch,
                max_image_side: c.max_image_side,
                max_image_pixels: c.max_image_pixels,
                max_upload_bytes: c.max_upload_bytes,
                max_indices: validate::MAX_INDICES as u32,
                max_buffered_bytes: self.scheduler.budget(),
                max_request_bytes: c.max_request_bytes(),
                max_random_access_calls: c.max_random_access_calls as u32,
                max_connections: c.max_connections as u32,
                max_connections_per_peer: c.max_connections_per_peer as u32,
                max_calls_per_connection: c.max_calls_per_connection,
                idle_connection_timeout_s: c.idle_connection_timeout_s,
                stall_timeout_s: c.stall_timeout_s,
            }),
            workers: self.scheduler.workers() as u32,
            serving: self.is_serving(),
            simd: crate::isa::current().name().into(),
        }
    }
}
