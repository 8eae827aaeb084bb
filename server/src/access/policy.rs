//! Which role may make which call: one table of every API method and what it needs. The guard
//! (`super::guard`) consults it before a call reaches its service; the vehicle a detection call
//! names is checked by the detection service against the caller's scope (`super::Caller`). It
//! knows no identity and no request.

use super::roles::Role;

/// What a call needs of its caller.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Need {
    /// Detection for the vehicles it names: a vehicle (its own), a gateway (its vehicles) or an
    /// admin.
    Detect,
    /// Reading: an operator or an admin.
    Read,
    /// Changing what the fleet runs or stores: an admin.
    Admin,
}

impl Need {
    pub fn allows(self, role: Role) -> bool {
        match self {
            Need::Detect => matches!(role, Role::Vehicle | Role::Gateway | Role::Admin),
            Need::Read => matches!(role, Role::Operator | Role::Admin),
            Need::Admin => role == Role::Admin,
        }
    }
}

/// Every guarded method by its gRPC path, and what it needs.
pub const METHODS: &[(&str, Need)] = &[
    ("/spoofwatch.v1.DetectionService/StreamDetect", Need::Detect),
    ("/spoofwatch.v1.DetectionService/Detect", Need::Detect),
    (
        "/spoofwatch.v1.DetectionService/StreamDetectFleet",
        Need::Detect,
    ),
    ("/spoofwatch.v1.DetectionService/ListSessions", Need::Read),
    ("/spoofwatch.v1.DetectionService/GetSession", Need::Read),
    // A reset forgets a vehicle's calibration and ends its alarm: never a vehicle's own choice
    // through this call (a stream may still start over with `reset`, for its own vehicle only).
    ("/spoofwatch.v1.DetectionService/ResetSession", Need::Admin),
    ("/spoofwatch.v1.ModelService/ListModels", Need::Read),
    ("/spoofwatch.v1.ModelService/GetModel", Need::Read),
    ("/spoofwatch.v1.ModelService/ExportModel", Need::Read),
    ("/spoofwatch.v1.ModelService/SetActiveModel", Need::Admin),
    ("/spoofwatch.v1.ModelService/DeleteModel", Need::Admin),
    ("/spoofwatch.v1.ModelService/ImportModel", Need::Admin),
    // A shadow costs CPU on every replica and its alarms are read beside the real ones.
    ("/spoofwatch.v1.ModelService/StartShadow", Need::Admin),
    ("/spoofwatch.v1.ModelService/StopShadow", Need::Admin),
    ("/spoofwatch.v1.ModelService/GetShadow", Need::Read),
    ("/spoofwatch.v1.ModelService/ListShadowAlarms", Need::Read),
    ("/spoofwatch.v1.DatasetService/UploadDataset", Need::Admin),
    ("/spoofwatch.v1.DatasetService/ImportDataset", Need::Admin),
    ("/spoofwatch.v1.DatasetService/ListDatasets", Need::Read),
    ("/spoofwatch.v1.DatasetService/GetDataset", Need::Read),
    ("/spoofwatch.v1.DatasetService/DeleteDataset", Need::Admin),
    ("/spoofwatch.v1.AlarmService/ListAlarms", Need::Read),
    ("/spoofwatch.v1.AlarmService/WatchAlarms", Need::Read),
    ("/spoofwatch.v1.AlarmService/ListIncidents", Need::Read),
    ("/spoofwatch.v1.AlarmService/GetIncident", Need::Read),
    ("/spoofwatch.v1.AlarmService/WatchIncidents", Need::Read),
    // Ending an incident by hand changes how the fleet is scored (its area prior stops).
    ("/spoofwatch.v1.AlarmService/EndIncident", Need::Admin),
    (
        "/spoofwatch.v1.TrainingService/CreateTrainingJob",
        Need::Admin,
    ),
    (
        "/spoofwatch.v1.TrainingService/CreateEvaluationJob",
        Need::Admin,
    ),
    ("/spoofwatch.v1.TrainingService/WatchJob", Need::Read),
    ("/google.longrunning.Operations/ListOperations", Need::Read),
    ("/google.longrunning.Operations/GetOperation", Need::Read),
    ("/google.longrunning.Operations/WaitOperation", Need::Read),
    (
        "/google.longrunning.Operations/DeleteOperation",
        Need::Admin,
    ),
    (
        "/google.longrunning.Operations/CancelOperation",
        Need::Admin,
    ),
];

/// The method's need and its table entry (for metric labels); a path not in the table (no such
/// method: the service answers UNIMPLEMENTED) needs an admin, so that only an admin learns which
/// methods exist.
pub fn need_of(path: &str) -> (&'static str, Need) {
    METHODS
        .iter()
        .find(|(method, _)| *method == path)
        .map_or(("unknown", Need::Admin), |&(method, need)| (method, need))
}

#[cfg(test)]
mod tests {
    use prost::Message;

    use super::*;

    /// Every method of every served API service (from the compiled schema), as gRPC paths.
    fn served_methods() -> Vec<String> {
        let set = prost_types::FileDescriptorSet::decode(spoofwatch_proto::FILE_DESCRIPTOR_SET)
            .expect("the embedded descriptor set decodes");
        let mut paths = Vec::new();
        for file in set.file {
            for service in &file.service {
                for method in &service.method {
                    paths.push(format!(
                        "/{}.{}/{}",
                        file.package(),
                        service.name(),
                        method.name()
                    ));
                }
            }
        }
        paths
    }

    #[test]
    fn every_served_method_is_in_the_table_once() {
        let served = served_methods();
        assert_eq!(served.len(), METHODS.len(), "{served:?}");
        for path in &served {
            let entries = METHODS.iter().filter(|(m, _)| m == path).count();
            assert_eq!(entries, 1, "{path}");
        }
    }

    #[test]
    fn each_need_admits_exactly_its_roles() {
        let admitted = |need: Need| -> Vec<Role> {
            Role::ALL.into_iter().filter(|r| need.allows(*r)).collect()
        };
        assert_eq!(
            admitted(Need::Detect),
            [Role::Vehicle, Role::Gateway, Role::Admin]
        );
        assert_eq!(admitted(Need::Read), [Role::Operator, Role::Admin]);
        assert_eq!(admitted(Need::Admin), [Role::Admin]);
        assert_eq!(
            need_of("/spoofwatch.v1.Nope/Nothing"),
            ("unknown", Need::Admin)
        );
    }
}
