//! The cell's node manager: owns the cell's namespace, and answers method calls by
//! asking the cell over zenoh (a PackML request to a resource, a work order to the
//! order-nodes), with the status codes of docs/opcua.md.
//!
//! Each Call service request runs in its own task inside async-opcua, so a call waiting
//! for a resource's answer blocks no read, publish or other session. The address
//! space's lock is never held across an await.

use std::sync::Arc;
use std::time::Duration;

use async_trait::async_trait;
use futures_util::future::join_all;
use opcua::sync::RwLock;
use opcua::types::{IdType, Identifier, StatusCode, TimestampsToReturn, Variant};
use opcua_server::address_space::AddressSpace;
use opcua_server::diagnostics::NamespaceMetadata;
use opcua_server::node_manager::memory::{
    InMemoryNodeManager, InMemoryNodeManagerBuilder, InMemoryNodeManagerImpl,
    InMemoryNodeManagerImplBuilder,
};
use opcua_server::node_manager::{MethodCall, RequestContext, ServerContext};
use opcua_server::CreateMonitoredItem;
use schemas::{CellKeys, PackmlCommand, PackmlReply, PackmlRequest, Refusal, UnitMode, WorkOrder};
use tracing::{info, warn};

use super::address_space::{self, MethodTarget};
use super::users::{CellAuth, Role};

/// How long a method call waits for the cell's answer (below asyncua's default request
/// timeout of 4 s, so the client gets our BadTimeout rather than its own).
pub const ANSWER_WITHIN: Duration = Duration::from_secs(3);

/// The sampling interval every data monitored item of the cell's namespace gets (ms):
/// as good as 0 (every change), which async-opcua's revision does not allow.
pub const PUSHED_SAMPLING_MS: f64 = 0.001;

/// The node manager of the cell's namespace.
pub type CellNodeManager = InMemoryNodeManager<CellNodes>;

/// What the cell's node manager needs to answer calls.
pub struct CellNodes {
    /// Our namespace's index.
    ns: u16,
    /// Our namespace's URI.
    uri: String,
    /// The cell's zenoh session.
    session: zenoh::Session,
    /// The cell's keys.
    keys: CellKeys,
    /// Who may call methods.
    auth: Arc<CellAuth>,
}

/// The builder of the cell's node manager, for `ServerBuilder::with_node_manager`.
pub fn cell_nodes(
    uri: String,
    session: zenoh::Session,
    keys: CellKeys,
    auth: Arc<CellAuth>,
) -> InMemoryNodeManagerBuilder<impl InMemoryNodeManagerImplBuilder> {
    InMemoryNodeManagerBuilder::new(move |context: ServerContext, space: &mut AddressSpace| {
        let ns = context
            .type_tree
            .write()
            .namespaces_mut()
            .add_namespace(&uri);
        space.add_namespace(&uri, ns);
        address_space::add_static(space, ns);
        CellNodes {
            ns,
            uri,
            session,
            keys,
            auth,
        }
    })
}

/// A call's outcome: its outputs, or a Bad status code.
type Outcome = Result<Vec<Variant>, StatusCode>;

/// The PackML command of a method's browse name.
fn command_of(method: &str) -> Option<PackmlCommand> {
    Some(match method {
        "Start" => PackmlCommand::Start,
        "Stop" => PackmlCommand::Stop,
        "Hold" => PackmlCommand::Hold,
        "Unhold" => PackmlCommand::Unhold,
        "Suspend" => PackmlCommand::Suspend,
        "Unsuspend" => PackmlCommand::Unsuspend,
        "Abort" => PackmlCommand::Abort,
        "Clear" => PackmlCommand::Clear,
        "Reset" => PackmlCommand::Reset,
        _ => return None,
    })
}

/// The status code of a resource's refusal (docs/opcua.md).
pub fn refusal_status(refusal: &Refusal) -> StatusCode {
    match refusal {
        Refusal::NotInState { .. } | Refusal::ModeNotInState { .. } => StatusCode::BadInvalidState,
        // Suspend/Unsuspend: the resource suspends by itself; the command exists in
        // PackML but this unit does not implement it.
        Refusal::NotSupported { .. } => StatusCode::BadNotSupported,
        // Refusals of other requests (none of a command or a mode change today).
        #[allow(unreachable_patterns)]
        _ => StatusCode::BadInvalidState,
    }
}

impl CellNodes {
    async fn call_one(&self, context: &RequestContext, call: &mut MethodCall) {
        let who = CellAuth::who(&context.token);
        let target = match &call.method_id().identifier {
            Identifier::String(path) if call.method_id().namespace == self.ns => {
                address_space::method_target(path.as_ref())
            }
            _ => None,
        };
        // async-opcua asked `is_user_executable` already; this is the second check.
        let outcome = if self.auth.role_of(&context.token) != Some(Role::Operator) {
            warn!(%who, method = %call.method_id(), "method call refused: only operators call methods (BadUserAccessDenied)");
            Err(StatusCode::BadUserAccessDenied)
        } else {
            match &target {
                Some(MethodTarget::Resource { resource, method }) => {
                    self.resource_method(&who, resource, method, call.arguments())
                        .await
                }
                Some(MethodTarget::Cell { method })
                    if method == address_space::SUBMIT_WORK_ORDER =>
                {
                    self.submit(&who, call.arguments()).await
                }
                _ => Err(StatusCode::BadMethodInvalid),
            }
        };
        let from = context
            .session
            .read()
            .peer_address()
            .map(|a| a.to_string())
            .unwrap_or_else(|| "unknown".into());
        self.auth.record(super::audit::call_record(
            CellAuth::user_name(&context.token),
            &from,
            target.as_ref(),
            call.arguments(),
            &outcome,
        ));
        match outcome {
            Ok(outputs) => {
                call.set_outputs(outputs);
                call.set_status(StatusCode::Good);
            }
            Err(status) => call.set_status(status),
        }
    }

    async fn resource_method(
        &self,
        who: &str,
        resource: &str,
        method: &str,
        arguments: &[Variant],
    ) -> Outcome {
        let request = if method == address_space::SET_UNIT_MODE {
            let [Variant::Int32(number)] = arguments else {
                warn!(%who, resource, "SetUnitMode wants one Int32 (BadTypeMismatch)");
                return Err(StatusCode::BadTypeMismatch);
            };
            let Some(mode) = UnitMode::from_number(*number) else {
                warn!(%who, resource, mode = number, "SetUnitMode: no such unit mode (1 Production, 2 Maintenance, 3 Manual; BadInvalidArgument)");
                return Err(StatusCode::BadInvalidArgument);
            };
            PackmlRequest::mode(mode, who)
        } else {
            let Some(command) = command_of(method) else {
                return Err(StatusCode::BadMethodInvalid);
            };
            PackmlRequest::command(command, who)
        };
        let reply = self.ask_resource(resource, &request).await?;
        match &reply.refused {
            None => {
                info!(%who, resource, method, state = %reply.state, "PackML request accepted");
                Ok(Vec::new())
            }
            Some(refusal) => {
                let status = refusal_status(refusal);
                warn!(%who, resource, method, %refusal, status = %status, "PackML request refused by the resource; nothing changed");
                Err(status)
            }
        }
    }

    /// Sends one PackML request (never again on its own: commands are not idempotent).
    async fn ask_resource(
        &self,
        resource: &str,
        request: &PackmlRequest,
    ) -> Result<PackmlReply, StatusCode> {
        let payload = serde_json::to_vec(request).map_err(|_| StatusCode::BadInternalError)?;
        let replies = self
            .session
            .get(self.keys.packml(resource))
            .payload(payload)
            .timeout(ANSWER_WITHIN)
            .with(holon::query::replies())
            .await;
        let mut replies = match replies {
            Ok(replies) => replies,
            Err(e) => {
                warn!(resource, error = %e, "cannot send the PackML request (BadCommunicationError); nothing was asked");
                return Err(StatusCode::BadCommunicationError);
            }
        };
        let Some(reply) =
            tokio::time::timeout(ANSWER_WITHIN + Duration::from_millis(500), replies.recv())
                .await
                .ok()
                .flatten()
        else {
            warn!(resource, "the resource did not answer the PackML request (BadTimeout); it may or may not have taken: see its Status");
            return Err(StatusCode::BadTimeout);
        };
        match reply.result() {
            Ok(sample) => serde_json::from_slice(&sample.payload().to_bytes()).map_err(|e| {
                warn!(resource, error = %e, "the resource answered what is not a PackML reply (BadInternalError)");
                StatusCode::BadInternalError
            }),
            Err(err) => {
                let text = err.payload().try_to_string().unwrap_or_default();
                warn!(resource, answer = %text, "the resource rejected the PackML request (BadRequestNotAllowed)");
                Err(StatusCode::BadRequestNotAllowed)
            }
        }
    }

    /// `SubmitWorkOrder(product, count, priority[, submitId])`: the fourth argument is
    /// optional (clients of the three-argument method call it as before); `''` is none.
    async fn submit(&self, who: &str, arguments: &[Variant]) -> Outcome {
        let ([Variant::String(product), Variant::Int32(count), Variant::Int32(priority)]
        | [Variant::String(product), Variant::Int32(count), Variant::Int32(priority), Variant::String(_)]) =
            arguments
        else {
            warn!(%who, "SubmitWorkOrder wants (String, Int32, Int32[, String]) (BadTypeMismatch)");
            return Err(StatusCode::BadTypeMismatch);
        };
        let submit_id = match arguments.get(3) {
            Some(Variant::String(id)) if !id.is_empty() => Some(id.as_ref().to_string()),
            _ => None,
        };
        let product = product.as_ref().to_string();
        let work = WorkOrder {
            product: product.clone(),
            count: (*count).max(0) as u32,
            priority: *priority,
            due: None,
            queue: false,
            submit_id,
        };
        // The work order's own rules (a product name, count 1 to 10000, priority -1000
        // to 1000, a submitId that is a name), as the order-node checks them.
        if work.validate().is_err() {
            warn!(%who, %product, count, priority, "SubmitWorkOrder: a product, count 1 to 10000, priority -1000 to 1000 and a submitId of 1 to 64 of a-z, 0-9, '_', '-' (BadInvalidArgument)");
            return Err(StatusCode::BadInvalidArgument);
        }
        let key = self.keys.orders_submit();
        let payload = serde_json::to_vec(&work).map_err(|_| StatusCode::BadInternalError)?;
        let reply = match crate::client::ask::until_answered(
            &self.session,
            &key,
            Some(payload),
            who,
            ANSWER_WITHIN,
        )
        .await
        {
            Ok(Some(reply)) if crate::client::ask::timed_out(&reply) => {
                warn!(%who, %product, "the order-node did not answer the work order in time (BadTimeout): its orders may have been made all the same; cell orders lists them");
                return Err(StatusCode::BadTimeout);
            }
            Ok(Some(reply)) => reply,
            Ok(None) => {
                warn!(%who, %product, "no order-node was reached with the work order (BadTimeout); no order was made");
                return Err(StatusCode::BadTimeout);
            }
            Err(e) => {
                warn!(%who, %product, error = %e, "cannot send the work order (BadCommunicationError)");
                return Err(StatusCode::BadCommunicationError);
            }
        };
        match reply.result() {
            Ok(sample) => {
                let orders = serde_json::from_slice::<schemas::SubmitReply>(&sample.payload().to_bytes())
                    .map_err(|e| {
                        warn!(error = %e, "the order-node answered what is not a submit reply (BadInternalError)");
                        StatusCode::BadInternalError
                    })?
                    .orders;
                info!(%who, %product, count, priority, orders = ?orders, "work order submitted");
                Ok(vec![Variant::from(orders)])
            }
            Err(err) => {
                let text = err.payload().try_to_string().unwrap_or_default();
                let (code, message) = match serde_json::from_str::<schemas::ErrorReply>(&text) {
                    Ok(e) => (e.code, e.message),
                    Err(_) => (schemas::ErrorCode::Other(String::new()), text.to_string()),
                };
                let status = if code == schemas::ErrorCode::Unavailable {
                    StatusCode::BadResourceUnavailable
                } else {
                    StatusCode::BadInvalidArgument
                };
                warn!(%who, %product, %code, reason = %message, status = %status, "the order-node refused the work order; no order was made");
                Err(status)
            }
        }
    }
}

#[async_trait]
impl InMemoryNodeManagerImpl for CellNodes {
    async fn init(&self, _space: &mut AddressSpace, _context: ServerContext) {}

    fn name(&self) -> &str {
        "holarchy-cell"
    }

    fn namespaces(&self) -> Vec<NamespaceMetadata> {
        vec![NamespaceMetadata {
            namespace_uri: self.uri.clone(),
            namespace_index: self.ns,
            static_node_id_types: Some(vec![IdType::String]),
            ..Default::default()
        }]
    }

    /// As async-opcua's default (the current value, Good), and every data monitored
    /// item samples every 1 µs: our values are pushed on change, not sampled, and
    /// async-opcua 0.19 holds back a change that comes within the sampling interval of
    /// the one before and may never deliver it (Aborting then Aborted 1 ms apart stayed
    /// Aborting for a client sampling every 50 ms, asyncua's default).
    async fn create_value_monitored_items(
        &self,
        context: &RequestContext,
        space: &RwLock<AddressSpace>,
        items: &mut [&mut &mut CreateMonitoredItem],
    ) {
        let to_read: Vec<_> = items.iter().map(|item| item.item_to_monitor()).collect();
        let values = self
            .read_values(context, space, &to_read, 0.0, TimestampsToReturn::Both)
            .await;
        for (value, item) in values.into_iter().zip(items.iter_mut()) {
            if value.status() != StatusCode::BadAttributeIdInvalid {
                item.set_initial_value(value);
            }
            item.set_status(StatusCode::Good);
            item.revise_sampling_interval(PUSHED_SAMPLING_MS);
        }
    }

    async fn call(
        &self,
        context: &RequestContext,
        _space: &RwLock<AddressSpace>,
        methods: &mut [&mut &mut MethodCall],
    ) -> Result<(), StatusCode> {
        join_all(methods.iter_mut().map(|call| self.call_one(context, call))).await;
        Ok(())
    }
}
