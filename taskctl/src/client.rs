//! A blocking client of the task controller service, for the actor and learner processes
//! (their loops are plain threads; calls run on a tokio runtime they pass in).

use std::sync::Arc;
use std::time::Duration;

use proto::convert::track_from_proto;
use proto::security::{AddToken, MAX_MESSAGE_BYTES};
use proto::v1;
use proto::v1::task_controller_client::TaskControllerClient;
use sim::Track;
use tokio::runtime::Handle;
use tonic::codegen::InterceptedService;
use tonic::transport::Channel;

/// An actor's environments as the task controller assigned them.
#[derive(Clone, Debug)]
pub struct Registration {
    /// Global index of the first environment.
    pub first_env: usize,
    /// Their current tracks.
    pub tracks: Vec<Arc<Track>>,
    /// Rollout index of the next report.
    pub next_rollout: u64,
}

/// A call that failed, and whether trying again can help.
#[derive(Debug, thiserror::Error)]
#[error("task controller: {message}{}", if *.transient { " (transient)" } else { "" })]
pub struct ClientError {
    /// The controller is unreachable, restarting or timed out: the same call may succeed
    /// later. Otherwise it refused the request itself and will refuse it again.
    pub transient: bool,
    /// What the server (or the connection) said.
    pub message: String,
}

impl From<tonic::Status> for ClientError {
    /// The one place gRPC status codes are read on the client side.
    fn from(s: tonic::Status) -> Self {
        use tonic::Code::{Cancelled, DeadlineExceeded, Unavailable, Unknown};
        let transient = matches!(s.code(), Unavailable | DeadlineExceeded | Unknown | Cancelled);
        Self { transient, message: format!("{:?}: {}", s.code(), s.message()) }
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
    pub fn new(runtime: Handle, url: &str, security: &proto::Security) -> Result<Self, proto::SecurityError> {
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
    ) -> Result<T, ClientError> {
        match self.runtime.block_on(async move { tokio::time::timeout(timeout, f).await }) {
            Ok(r) => Ok(r?.into_inner()),
            Err(_) => Err(ClientError { transient: true, message: format!("no answer within {timeout:?}") }),
        }
    }

    /// Registers actor `actor` with `envs` environments.
    pub fn register(&self, actor: &str, envs: usize) -> Result<Registration, ClientError> {
        let mut c = self.client.clone();
        let r = self.call(Duration::from_secs(30), c.register(v1::RegisterRequest { actor: actor.into(), envs: envs as u32 }))?;
        let tracks = r.tracks.iter().map(|t| track_from_proto(t).map(Arc::new)).collect::<Result<Vec<_>, _>>();
        let tracks = tracks.map_err(|message| ClientError { transient: false, message })?;
        if tracks.len() != envs {
            return Err(ClientError { transient: false, message: format!("{} tracks for {envs} environments", tracks.len()) });
        }
        Ok(Registration { first_env: r.first_env as usize, tracks, next_rollout: r.next_rollout })
    }

    /// Reports one rollout's cumulative rewards; returns `(global env, new track)` switches.
    pub fn report(&self, actor: &str, rollout: u64, rewards: &[f64]) -> Result<Vec<(usize, Arc<Track>)>, ClientError> {
        let mut c = self.client.clone();
        let request = v1::ReportRequest { actor: actor.into(), rollout, cumulative_rewards: rewards.to_vec() };
        let r = self.call(Duration::from_secs(30), c.report(request))?;
        r.switches
            .iter()
            .map(|a| {
                let track = a.track.as_ref().ok_or_else(|| "switch without a track".to_string()).and_then(track_from_proto);
                track.map(|t| (a.env as usize, Arc::new(t))).map_err(|message| ClientError { transient: false, message })
            })
            .collect()
    }

    /// Every environment's task.
    pub fn list_tasks(&self) -> Result<Vec<v1::Task>, ClientError> {
        let mut c = self.client.clone();
        Ok(self.call(Duration::from_secs(5), c.list_tasks(v1::ListTasksRequest {}))?.tasks)
    }

    /// Counts over all environments (no tracks travel).
    pub fn summary(&self) -> Result<v1::Summary, ClientError> {
        let mut c = self.client.clone();
        self.call(Duration::from_secs(5), c.get_summary(v1::SummaryRequest {}))
    }

    /// One environment's task.
    pub fn get_task(&self, env: usize) -> Result<v1::Task, ClientError> {
        let mut c = self.client.clone();
        self.call(Duration::from_secs(5), c.get_task(v1::GetTaskRequest { env: env as u32 }))
    }

    /// Switches from index `from` on, oldest first.
    pub fn switch_history(&self, from: u64) -> Result<Vec<v1::SwitchEvent>, ClientError> {
        let mut c = self.client.clone();
        Ok(self.call(Duration::from_secs(5), c.get_switch_history(v1::SwitchHistoryRequest { from }))?.events)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_unreachable_controller_is_transient_and_a_refusal_is_not() {
        assert!(ClientError::from(tonic::Status::unavailable("connection refused")).transient);
        assert!(ClientError::from(tonic::Status::deadline_exceeded("slow")).transient);
        let refused = ClientError::from(tonic::Status::invalid_argument("2 environments but reported 1 rewards"));
        assert!(!refused.transient);
        assert_eq!(refused.to_string(), "task controller: InvalidArgument: 2 environments but reported 1 rewards");
    }
}
