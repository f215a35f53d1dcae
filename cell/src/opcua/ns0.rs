//! A hand-made, minimal namespace 0 (async-opcua's `base-server` build has no generated
//! address space; the generated one costs about 2 min of build and 10 MB of binary).
//!
//! Without it the server has no Root or Objects folder, no Server object, no
//! NamespaceArray and no reference-type hierarchy in the type tree (so a Browse with
//! HierarchicalReferences and includeSubtypes finds nothing), and asyncua, which reads
//! `Server_ServerStatus_State` (i=2259) every second, drops the connection. What is here:
//! the reference types' hierarchy, FolderType, BaseObjectType's subtypes used,
//! Root/Objects/Types/Views, and Server with ServerArray, NamespaceArray and ServerStatus
//! (State, CurrentTime). docs/opcua.md says what a generic client may miss.

use async_trait::async_trait;
use opcua::sync::RwLock;
use opcua::types::{
    DataTypeId, DataValue, DateTime, IdType, NodeClass, NodeId, ObjectId, ObjectTypeId,
    ReferenceTypeId, StatusCode, TimestampsToReturn, VariableId, VariableTypeId, Variant,
};
use opcua_server::{
    address_space::{AddressSpace, ObjectBuilder, VariableBuilder},
    diagnostics::NamespaceMetadata,
    node_manager::{
        memory::{InMemoryNodeManagerBuilder, InMemoryNodeManagerImpl},
        ParsedReadValueId, RequestContext, ServerContext,
    },
};

/// The node manager of namespace 0.
pub struct MiniCore;

/// The builder of namespace 0, for `ServerBuilder::with_node_manager`.
pub fn mini_core() -> InMemoryNodeManagerBuilder<
    impl opcua_server::node_manager::memory::InMemoryNodeManagerImplBuilder,
> {
    InMemoryNodeManagerBuilder::new(|ctx: ServerContext, space: &mut AddressSpace| {
        space.add_namespace("http://opcfoundation.org/UA/", 0);
        // Reference type + a few object/variable types, so subtype checks work.
        {
            let mut tt = ctx.type_tree.write();
            use ReferenceTypeId as R;
            let rt = NodeClass::ReferenceType;
            for (child, parent) in [
                (R::HierarchicalReferences, R::References),
                (R::NonHierarchicalReferences, R::References),
                (R::HasChild, R::HierarchicalReferences),
                (R::Organizes, R::HierarchicalReferences),
                (R::HasEventSource, R::HierarchicalReferences),
                (R::HasNotifier, R::HasEventSource),
                (R::Aggregates, R::HasChild),
                (R::HasSubtype, R::HasChild),
                (R::HasComponent, R::Aggregates),
                (R::HasProperty, R::Aggregates),
                (R::HasOrderedComponent, R::HasComponent),
                (R::HasTypeDefinition, R::NonHierarchicalReferences),
                (R::HasModellingRule, R::NonHierarchicalReferences),
                (R::HasEncoding, R::NonHierarchicalReferences),
                (R::GeneratesEvent, R::NonHierarchicalReferences),
            ] {
                tt.add_type_node(&child.into(), &parent.into(), rt);
            }
            tt.add_type_node(
                &ObjectTypeId::FolderType.into(),
                &ObjectTypeId::BaseObjectType.into(),
                NodeClass::ObjectType,
            );
            tt.add_type_node(
                &ObjectTypeId::ServerType.into(),
                &ObjectTypeId::BaseObjectType.into(),
                NodeClass::ObjectType,
            );
            for v in [
                VariableTypeId::BaseDataVariableType,
                VariableTypeId::PropertyType,
            ] {
                tt.add_type_node(
                    &v.into(),
                    &VariableTypeId::BaseVariableType.into(),
                    NodeClass::VariableType,
                );
            }
        }
        // Root, Objects, Types, Views, Server{ServerArray, NamespaceArray, ServerStatus{State, CurrentTime}}
        let root: NodeId = ObjectId::RootFolder.into();
        ObjectBuilder::new(&root, "Root", "Root")
            .is_folder()
            .insert(space);
        for (id, name) in [
            (ObjectId::ObjectsFolder, "Objects"),
            (ObjectId::TypesFolder, "Types"),
            (ObjectId::ViewsFolder, "Views"),
        ] {
            ObjectBuilder::new(&id.into(), name, name)
                .is_folder()
                .organized_by(root.clone())
                .insert(space);
        }
        let server: NodeId = ObjectId::Server.into();
        ObjectBuilder::new(&server, "Server", "Server")
            .has_type_definition(ObjectTypeId::ServerType)
            .organized_by(ObjectId::ObjectsFolder)
            .insert(space);
        for (id, name) in [
            (VariableId::Server_ServerArray, "ServerArray"),
            (VariableId::Server_NamespaceArray, "NamespaceArray"),
        ] {
            VariableBuilder::new(&id.into(), name, name)
                .property_of(server.clone())
                .has_type_definition(VariableTypeId::PropertyType)
                .data_type(DataTypeId::String)
                .value_rank(1)
                .array_dimensions(&[0])
                .insert(space);
        }
        let status: NodeId = VariableId::Server_ServerStatus.into();
        VariableBuilder::new(&status, "ServerStatus", "ServerStatus")
            .component_of(server.clone())
            .data_type(DataTypeId::ServerStatusDataType)
            .insert(space);
        VariableBuilder::new(
            &VariableId::Server_ServerStatus_State.into(),
            "State",
            "State",
        )
        .component_of(status.clone())
        .data_type(DataTypeId::ServerState)
        .value(0i32) // Running
        .insert(space);
        VariableBuilder::new(
            &VariableId::Server_ServerStatus_CurrentTime.into(),
            "CurrentTime",
            "CurrentTime",
        )
        .component_of(status)
        .data_type(DataTypeId::UtcTime)
        .insert(space);
        MiniCore
    })
}

#[async_trait]
impl InMemoryNodeManagerImpl for MiniCore {
    async fn init(&self, _space: &mut AddressSpace, _ctx: ServerContext) {}
    fn name(&self) -> &str {
        "ns0"
    }
    fn namespaces(&self) -> Vec<NamespaceMetadata> {
        vec![NamespaceMetadata {
            namespace_uri: "http://opcfoundation.org/UA/".to_owned(),
            namespace_index: 0,
            static_node_id_types: Some(vec![IdType::Numeric]),
            ..Default::default()
        }]
    }

    async fn read_values(
        &self,
        context: &RequestContext,
        address_space: &RwLock<AddressSpace>,
        nodes: &[&ParsedReadValueId],
        max_age: f64,
        ts: TimestampsToReturn,
    ) -> Vec<DataValue> {
        let space = address_space.read();
        nodes
            .iter()
            .map(|n| {
                let special: Option<Variant> = if n.node_id == VariableId::Server_NamespaceArray {
                    let tt = context.type_tree.read();
                    let map = tt.namespaces().known_namespaces();
                    let max = map.values().copied().max().unwrap_or(0);
                    let mut v = vec![String::new(); max as usize + 1];
                    for (uri, idx) in map {
                        v[*idx as usize] = uri.clone();
                    }
                    Some(v.into())
                } else if n.node_id == VariableId::Server_ServerArray {
                    Some(vec![context.info.application_uri.to_string()].into())
                } else if n.node_id == VariableId::Server_ServerStatus_CurrentTime {
                    Some(DateTime::now().into())
                } else {
                    None
                };
                match special {
                    Some(v) => {
                        let mut dv = DataValue::new_now(v);
                        dv.status = Some(StatusCode::Good);
                        dv
                    }
                    None => space.read(context, n, max_age, ts),
                }
            })
            .collect()
    }
}
