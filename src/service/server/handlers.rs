//! The generated service's handlers ([`Service`]): thin, each a call of [`State`] and its
//! reply; the sample streams are answered in front of them, by the sample routes.

use std::sync::atomic::Ordering;
use std::sync::Arc;

use tonic::{Request, Response, Status, Streaming};

use super::admission::{client_of, refused, CallKind};
use super::routes::{GET_SAMPLES_PATH, STREAM_SAMPLES_PATH};
use super::state::State;
use crate::service::error::ServiceError;
use crate::service::pb;
use crate::service::pb::mpi_flow_server::MpiFlow;
use crate::service::reply::ReplyHold;

/// The tonic service.
#[derive(Clone, Debug)]
pub struct Service {
    pub(super) state: Arc<State>,
}

#[tonic::async_trait]
impl MpiFlow for Service {
    // StreamSamples and GetSamples are answered by `SampleRoutes`, which takes their paths before
    // this service sees a request; the generated trait still requires a handler for each, so
    // both are one refusal that names the route serving them.
    type StreamSamplesStream = tokio_stream::Empty<Result<pb::SampleBatch, Status>>;
    type GetSamplesStream = tokio_stream::Empty<Result<pb::Sample, Status>>;

    async fn stream_samples(
        &self,
        _request: Request<pb::StreamRequest>,
    ) -> Result<Response<Self::StreamSamplesStream>, Status> {
        Err(served_by_sample_routes(STREAM_SAMPLES_PATH))
    }

    async fn get_sample(&self, request: Request<pb::SampleRequest>) -> Result<Response<pb::Sample>, Status> {
        if self.state.draining.load(Ordering::SeqCst) {
            return Err(refused::<()>(&self.state, Err(ServiceError::Draining)).unwrap_err());
        }
        let client = client_of(&request);
        let admitted = refused(&self.state, self.state.admit(CallKind::RandomAccess, client.peer))?;
        let r = self.state.one_sample(request.get_ref(), client).await;
        let (sample, stream) = r.inspect_err(|s| self.state.metrics.count_refused(s.code()))?;
        let mut response = Response::new(sample);
        // the sample's bytes and the call's slot are held until the reply has been sent
        response.extensions_mut().insert(ReplyHold(Arc::new(std::sync::Mutex::new((stream, admitted)))));
        Ok(response)
    }

    async fn get_samples(
        &self,
        _request: Request<pb::SamplesRequest>,
    ) -> Result<Response<Self::GetSamplesStream>, Status> {
        Err(served_by_sample_routes(GET_SAMPLES_PATH))
    }

    async fn upload_sources(
        &self,
        request: Request<Streaming<pb::SourceChunk>>,
    ) -> Result<Response<pb::UploadSummary>, Status> {
        let r = self.state.upload(request.into_inner()).await;
        refused(&self.state, r).map(Response::new)
    }

    async fn get_info(&self, _request: Request<pb::InfoRequest>) -> Result<Response<pb::InfoResponse>, Status> {
        Ok(Response::new(self.state.info()))
    }
}

/// The answer of the generated handlers of the calls
/// [`SampleRoutes`](super::routes::SampleRoutes) serves: a request for `path` reaches
/// `SampleRoutes` first and never the generated service, so this is an internal error if it is
/// ever sent.
fn served_by_sample_routes(path: &str) -> Status {
    Status::internal(format!("{path} is served by the sample routes, not the generated service"))
}
