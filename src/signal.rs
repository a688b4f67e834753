//! The process's stop flag: SIGINT and SIGTERM ask every loop of the process to finish cleanly
//! (the learner checkpoints first).

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use anyhow::Context;

/// The process's stop flag, raised by SIGINT/SIGTERM. The handler is installed by the first
/// call; later calls share the same flag.
pub fn stop_flag() -> anyhow::Result<Arc<AtomicBool>> {
    static STOP: std::sync::Mutex<Option<Arc<AtomicBool>>> = std::sync::Mutex::new(None);
    let mut installed = STOP.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
    if let Some(stop) = installed.as_ref() {
        return Ok(stop.clone());
    }
    let stop = Arc::new(AtomicBool::new(false));
    let flag = stop.clone();
    ctrlc::set_handler(move || flag.store(true, Ordering::SeqCst)).context("installing the signal handler")?;
    *installed = Some(stop.clone());
    Ok(stop)
}
