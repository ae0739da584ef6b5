//! The generated service's handlers ([`Service`]): thin, each a call of [`State`] and its
//! reply. The sample streams (StreamSamples, GetSamples) are answered in front of the service,
//! by the sample routes, so it has no handler for them (the generated trait's default methods,
//! never reached, stand in their place).

use std::sync::atomic::Ordering;
use std::sync::Arc;

use tonic::{Request, Response, Status, Streaming};

use super::admission::{client_of, refused, CallKind};
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
