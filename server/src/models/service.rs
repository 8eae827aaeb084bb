//! The ModelService RPCs: the edge between the wire and the model [`Registry`]. Decodes and
//! validates requests, calls the registry and maps its errors once (through `crate::error`); it
//! must not hold registry logic or touch the store directly. Deleting a model ends the sessions
//! that run it: DeleteModel goes through a [`ModelDeletion`], which the detection sessions provide,
//! so that models need not know them. The shadow calls are carried out by `crate::shadow`; a
//! model under shadow is not deleted.

use std::pin::Pin;
use std::sync::Arc;

use spoofwatch_proto::v1;
use spoofwatch_proto::v1::model_service_server::ModelService;
use spoofwatch_proto::wire::limits::{EXPORT_CHUNK_BYTES, MAX_ARTIFACT_BYTES};
use tokio_stream::{Stream, StreamExt};
use tonic::{Request, Response, Status, Streaming};

use crate::access::Caller;
use crate::edge::{display_name, model_name, page_request};
use crate::idle::StreamIdle;
use spoofwatch_proto::wire::ModelName;

use super::Registry;
use super::wire::{model_summary_to_proto, model_to_proto};
use crate::shadow::Shadows;
use crate::shadow::service::{decode_start, shadow_id};
use crate::status::{failed_precondition, invalid_field};

/// Deletes a model (not the active one) and ends the sessions that use it, so that none starts on
/// it meanwhile; returns how many ended.
#[tonic::async_trait]
pub trait ModelDeletion: Send + Sync + std::fmt::Debug {
    async fn delete_and_end_sessions(&self, name: &ModelName) -> Result<usize, Status>;
}

/// The ModelService implementation.
#[derive(Debug, Clone)]
pub struct ModelApi {
    pub registry: Arc<Registry>,
    /// Deletes a model and ends the sessions that use it.
    pub deletion: Arc<dyn ModelDeletion>,
    /// How long an import may send nothing.
    pub stream_idle: StreamIdle,
    /// Shadow evaluation of candidate models.
    pub shadows: Arc<Shadows>,
}

type ChunkStream = Pin<Box<dyn Stream<Item = Result<v1::ModelChunk, Status>> + Send>>;

#[tonic::async_trait]
impl ModelService for ModelApi {
    async fn list_models(
        &self,
        request: Request<v1::ListModelsRequest>,
    ) -> Result<Response<v1::ListModelsResponse>, Status> {
        let r = request.into_inner();
        let page = self
            .registry
            .list(&page_request(r.page_size, &r.page_token)?)
            .await?;
        Ok(Response::new(v1::ListModelsResponse {
            models: page.items.iter().map(model_summary_to_proto).collect(),
            next_page_token: page.next_page_token.unwrap_or_default(),
        }))
    }

    async fn get_model(
        &self,
        request: Request<v1::GetModelRequest>,
    ) -> Result<Response<v1::Model>, Status> {
        let name = model_name("name", &request.into_inner().name)?;
        Ok(Response::new(model_to_proto(
            &self.registry.get(&name).await?,
        )))
    }

    async fn set_active_model(
        &self,
        request: Request<v1::SetActiveModelRequest>,
    ) -> Result<Response<v1::Model>, Status> {
        let name = model_name("name", &request.into_inner().name)?;
        Ok(Response::new(model_to_proto(
            &self.registry.activate(&name).await?,
        )))
    }

    async fn delete_model(
        &self,
        request: Request<v1::DeleteModelRequest>,
    ) -> Result<Response<()>, Status> {
        let name = model_name("name", &request.into_inner().name)?;
        if self.shadows.candidate().as_ref() == Some(&name) {
            return Err(failed_precondition(
                "MODEL_SHADOWED",
                format!("{name} is the running shadow's candidate: stop the shadow first"),
            ));
        }
        self.deletion.delete_and_end_sessions(&name).await?;
        Ok(Response::new(()))
    }

    type ExportModelStream = ChunkStream;

    async fn export_model(
        &self,
        request: Request<v1::ExportModelRequest>,
    ) -> Result<Response<Self::ExportModelStream>, Status> {
        let caller = Caller::of(&request)?;
        let name = model_name("name", &request.into_inner().name)?;
        let bytes = self.registry.artifact_bytes(&name).await?;
        let chunks: Vec<v1::ModelChunk> = bytes
            .chunks(EXPORT_CHUNK_BYTES)
            .map(|c| v1::ModelChunk { data: c.to_vec() })
            .collect();
        // A client that reads slowly keeps the export open: each chunk is sent only while the
        // identities in force still admit the caller, and a change that does not ends the export.
        let (mut caller, mut ended) = (caller, false);
        let sent = tokio_stream::iter(chunks).map_while(move |chunk| {
            if ended {
                return None;
            }
            let chunk = caller.check_standing(None).map(|()| chunk);
            ended = chunk.is_err();
            Some(chunk)
        });
        Ok(Response::new(Box::pin(sent)))
    }

    async fn import_model(
        &self,
        request: Request<Streaming<v1::ImportModelRequest>>,
    ) -> Result<Response<v1::Model>, Status> {
        use v1::import_model_request::Kind;
        // As an upload: a change of the identity files that no longer admits the caller ends the
        // import, and nothing is stored.
        let mut caller = Caller::of(&request)?;
        let mut stream = request.into_inner();
        let idle = self.stream_idle;
        let header = match caller.unless_revoked(None, idle.next(&mut stream)).await? {
            Some(v1::ImportModelRequest {
                kind: Some(Kind::Header(h)),
            }) => h,
            _ => return Err(crate::status::header_first()),
        };
        let mut bytes = Vec::new();
        while let Some(message) = caller.unless_revoked(None, idle.next(&mut stream)).await? {
            match message.kind {
                Some(Kind::Chunk(chunk)) => {
                    // Refused before the chunk is buffered: memory per import stays bounded.
                    if bytes.len() + chunk.len() > MAX_ARTIFACT_BYTES {
                        return Err(invalid_field(
                            "artifact",
                            format!(
                                "must be at most {} MiB; the upload went past it",
                                MAX_ARTIFACT_BYTES >> 20
                            ),
                        ));
                    }
                    bytes.extend_from_slice(&chunk);
                }
                _ => return Err(crate::status::header_not_first()),
            }
        }
        let name = display_name("header.display_name", &header.display_name)?;
        caller.check_standing(None)?;
        let row = self.registry.import(&bytes, name, header.activate).await?;
        Ok(Response::new(model_to_proto(&row)))
    }

    async fn start_shadow(
        &self,
        request: Request<v1::StartShadowRequest>,
    ) -> Result<Response<v1::Shadow>, Status> {
        let by = Caller::of(&request)?.credential.label;
        let (model, scope) = decode_start(request.get_ref())?;
        Ok(Response::new(self.shadows.start(&model, scope, &by).await?))
    }

    async fn get_shadow(
        &self,
        request: Request<v1::GetShadowRequest>,
    ) -> Result<Response<v1::Shadow>, Status> {
        let id = shadow_id("name", &request.into_inner().name)?;
        Ok(Response::new(self.shadows.get(id).await?))
    }

    async fn stop_shadow(
        &self,
        request: Request<v1::StopShadowRequest>,
    ) -> Result<Response<v1::Shadow>, Status> {
        let by = Caller::of(&request)?.credential.label;
        let id = shadow_id("name", &request.get_ref().name)?;
        Ok(Response::new(self.shadows.stop(id, &by).await?))
    }

    async fn list_shadow_alarms(
        &self,
        request: Request<v1::ListShadowAlarmsRequest>,
    ) -> Result<Response<v1::ListShadowAlarmsResponse>, Status> {
        Ok(Response::new(self.shadows.alarms(request.get_ref()).await?))
    }
}
