//! The task controller over gRPC, as a blocking [`TaskService`] for the actor and learner
//! processes (their loops are plain threads; calls run on a tokio runtime they pass in).

use std::sync::Arc;
use std::time::Duration;

use sim::Track;
use taskctl::{Registration, Summary, SwitchEvent, TaskInfo, TaskService, TaskServiceError};
use tokio::runtime::Handle;
use tonic::codegen::InterceptedService;
use tonic::transport::Channel;

use crate::convert::track_from_proto;
use crate::security::{AddToken, MAX_MESSAGE_BYTES};
use crate::task_grpc::{summary_from_proto, switch_from_proto, task_from_proto};
use proto::v1;
use proto::v1::task_controller_client::TaskControllerClient;

/// The one place gRPC status codes are read on the client side (the adapter's `status` writes
/// them): unreachable, restarting or slow is transient, a refusal is not.
fn status_error(s: tonic::Status) -> TaskServiceError {
    use tonic::Code::{Cancelled, DeadlineExceeded, Unavailable, Unknown};
    let message = format!("{:?}: {}", s.code(), s.message());
    if matches!(s.code(), Unavailable | DeadlineExceeded | Unknown | Cancelled) {
        TaskServiceError::Unavailable(message)
    } else {
        TaskServiceError::RefusedRemotely(message)
    }
}

/// Blocking task-controller client.
pub struct TaskClient {
    runtime: Handle,
    client: TaskControllerClient<InterceptedService<Channel, AddToken>>,
}

impl TaskClient {
    /// A client of the task controller at `url` (connects lazily, reconnects by itself). The
    /// runtime must be multi-threaded: calls block on its handle, which cannot drive a
    /// current-thread runtime's I/O.
    pub fn new(runtime: Handle, url: &str, security: &crate::Security) -> Result<Self, crate::SecurityError> {
        let channel = {
            let _guard = runtime.enter();
            security.channel(url)?
        };
        let client = TaskControllerClient::with_interceptor(channel, security.token_header())
            .max_decoding_message_size(MAX_MESSAGE_BYTES)
            .max_encoding_message_size(MAX_MESSAGE_BYTES);
        Ok(Self { runtime, client })
    }

    fn call<T>(
        &self,
        timeout: Duration,
        f: impl std::future::Future<Output = Result<tonic::Response<T>, tonic::Status>>,
    ) -> Result<T, TaskServiceError> {
        match self.runtime.block_on(async move { tokio::time::timeout(timeout, f).await }) {
            Ok(r) => Ok(r.map_err(status_error)?.into_inner()),
            Err(_) => Err(TaskServiceError::Unavailable(format!("no answer within {timeout:?}"))),
        }
    }
}

impl TaskService for TaskClient {
    fn register(&self, actor: &str, envs: usize) -> Result<Registration, TaskServiceError> {
        let mut c = self.client.clone();
        let r = self.call(Duration::from_secs(30), c.register(v1::RegisterRequest { actor: actor.into(), envs: envs as u32 }))?;
        let tracks = r.tracks.iter().map(|t| track_from_proto(t).map(Arc::new)).collect::<Result<Vec<_>, _>>();
        let tracks = tracks.map_err(|e| TaskServiceError::BadAnswer(e.to_string()))?;
        if tracks.len() != envs {
            return Err(TaskServiceError::BadAnswer(format!("{} tracks for {envs} environments", tracks.len())));
        }
        Ok(Registration { first_env: r.first_env as usize, tracks, next_rollout: r.next_rollout })
    }

    fn report(&self, actor: &str, rollout: u64, rewards: &[f64]) -> Result<Vec<(usize, Arc<Track>)>, TaskServiceError> {
        let mut c = self.client.clone();
        let request = v1::ReportRequest { actor: actor.into(), rollout, cumulative_rewards: rewards.to_vec() };
        let r = self.call(Duration::from_secs(30), c.report(request))?;
        r.switches
            .iter()
            .map(|a| {
                let track = a.track.as_ref().ok_or_else(|| TaskServiceError::BadAnswer("switch without a track".into()))?;
                let track = track_from_proto(track).map_err(|e| TaskServiceError::BadAnswer(e.to_string()))?;
                Ok((a.env as usize, Arc::new(track)))
            })
            .collect()
    }

    fn task(&self, env: usize) -> Result<TaskInfo, TaskServiceError> {
        let mut c = self.client.clone();
        let task = self.call(Duration::from_secs(5), c.get_task(v1::GetTaskRequest { env: env as u32 }))?;
        task_from_proto(&task)
    }

    fn tasks(&self) -> Result<Vec<TaskInfo>, TaskServiceError> {
        let mut c = self.client.clone();
        let tasks = self.call(Duration::from_secs(5), c.list_tasks(v1::ListTasksRequest {}))?.tasks;
        tasks.iter().map(task_from_proto).collect()
    }

    fn summary(&self) -> Result<Summary, TaskServiceError> {
        let mut c = self.client.clone();
        Ok(summary_from_proto(&self.call(Duration::from_secs(5), c.get_summary(v1::SummaryRequest {}))?))
    }

    fn switch_history(&self, from: u64) -> Result<Vec<SwitchEvent>, TaskServiceError> {
        let mut c = self.client.clone();
        let events = self.call(Duration::from_secs(5), c.get_switch_history(v1::SwitchHistoryRequest { from }))?.events;
        Ok(events.iter().map(switch_from_proto).collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_unreachable_controller_is_transient_and_a_refusal_is_not() {
        assert!(status_error(tonic::Status::unavailable("connection refused")).is_transient());
        assert!(status_error(tonic::Status::deadline_exceeded("slow")).is_transient());
        let refused = status_error(tonic::Status::invalid_argument("2 environments but reported 1 rewards"));
        assert!(!refused.is_transient());
        assert_eq!(refused.to_string(), "task controller: InvalidArgument: 2 environments but reported 1 rewards");
    }
}
