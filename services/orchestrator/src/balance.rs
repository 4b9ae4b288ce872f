//! Client-side load balancing over the instances of one stage service, with health checks.
//!
//! A stage service's endpoint may list several instances (`http://a:50054, http://b:50054`). Calls
//! go through tonic's power-of-two-choices balancer (two instances picked at random, the one with
//! fewer calls in flight gets the call). A background task asks every instance's
//! `grpc.health.v1.Health/Check` each interval: an instance that does not answer SERVING leaves the
//! balancer and comes back when it does. The last instance is never removed, so a total outage
//! fails calls at once (UNAVAILABLE, which the worker retries) instead of leaving them waiting.

use std::time::Duration;

use futures::future::join_all;
use tonic::transport::channel::Change;
use tonic::transport::{Channel, Endpoint};
use tonic_health::pb::HealthCheckRequest;
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::health_client::HealthClient;

/// A channel balancing over `endpoints` (at least one), health-checked every `interval`. Needs a
/// tokio runtime; the checks stop when the last clone of the channel is dropped.
pub(crate) fn balanced(service: &'static str, endpoints: Vec<Endpoint>, interval: Duration) -> Channel {
    let n = endpoints.len();
    let (channel, tx) = Channel::balance_channel::<usize>(2 * n.max(1));
    for (i, endpoint) in endpoints.iter().enumerate() {
        // The buffer holds every first insertion: cannot fail.
        let _ = tx.try_send(Change::Insert(i, endpoint.clone()));
    }
    metrics::gauge!("depthmill_stage_instances_healthy", "service" => service).set(n as f64);
    tokio::spawn(async move {
        let probes: Vec<HealthClient<Channel>> =
            endpoints.iter().map(|e| HealthClient::new(e.connect_lazy())).collect();
        let mut in_set = vec![true; n];
        let mut ticker = tokio::time::interval(interval);
        ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            ticker.tick().await;
            if tx.is_closed() {
                return;
            }
            let healthy = join_all(probes.iter().map(|p| serving(p.clone(), interval))).await;
            for (i, ok) in healthy.into_iter().enumerate() {
                let uri = endpoints[i].uri();
                if ok && !in_set[i] {
                    if tx.send(Change::Insert(i, endpoints[i].clone())).await.is_err() {
                        return;
                    }
                    in_set[i] = true;
                    tracing::info!(service, instance = %uri, "stage service instance is back");
                } else if !ok && in_set[i] && in_set.iter().filter(|x| **x).count() > 1 {
                    if tx.send(Change::Remove(i)).await.is_err() {
                        return;
                    }
                    in_set[i] = false;
                    tracing::warn!(service, instance = %uri, "stage service instance failed its health check; not calling it");
                }
            }
            let count = in_set.iter().filter(|x| **x).count();
            metrics::gauge!("depthmill_stage_instances_healthy", "service" => service).set(count as f64);
        }
    });
    channel
}

/// Whether the instance answers SERVING within `timeout`.
async fn serving(mut probe: HealthClient<Channel>, timeout: Duration) -> bool {
    let mut request = tonic::Request::new(HealthCheckRequest { service: String::new() });
    request.set_timeout(timeout);
    match tokio::time::timeout(timeout, probe.check(request)).await {
        Ok(Ok(answer)) => answer.into_inner().status == ServingStatus::Serving as i32,
        _ => false,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio_util::sync::CancellationToken;

    /// A server whose health service knows the extra service name `name`: asking the balanced
    /// channel for `name` tells which instance answered.
    async fn instance(listener: tokio::net::TcpListener, name: &'static str) -> CancellationToken {
        let token = CancellationToken::new();
        let stop = token.clone();
        tokio::spawn(async move {
            let names = [name];
            let routes = tonic::service::Routes::default();
            let _ = depthmill_common::grpc::serve_grpc(listener, routes, &names, stop.cancelled()).await;
        });
        token
    }

    /// How many of `calls` calls through `channel` reached the instance that knows `name`.
    async fn reached(channel: &Channel, name: &str, calls: usize) -> usize {
        let mut client = HealthClient::new(channel.clone());
        let mut hits = 0;
        for _ in 0..calls {
            let answer = client.check(HealthCheckRequest { service: name.into() }).await;
            hits += usize::from(answer.is_ok_and(|a| a.into_inner().status == ServingStatus::Serving as i32));
        }
        hits
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn calls_spread_over_instances_and_skip_a_dead_one_until_it_returns() -> anyhow::Result<()> {
        let a = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
        let b = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
        let (addr_a, addr_b) = (a.local_addr()?, b.local_addr()?);
        let _stop_a = instance(a, "instance-a").await;
        let stop_b = instance(b, "instance-b").await;
        let endpoints = [addr_a, addr_b]
            .iter()
            .map(|addr| Endpoint::from_shared(format!("http://{addr}")))
            .collect::<Result<Vec<_>, _>>()?;
        let interval = Duration::from_millis(100);
        let channel = balanced("test", endpoints, interval);

        // Both serve: both get calls.
        let to_a = reached(&channel, "instance-a", 40).await;
        assert!((5..=35).contains(&to_a), "{to_a} of 40 calls reached a");

        // b dies: after one health round every call goes to a, none fails.
        stop_b.cancel();
        tokio::time::sleep(interval * 4).await;
        assert_eq!(reached(&channel, "instance-a", 40).await, 40);

        // b comes back on its address: it gets calls again.
        let b = tokio::net::TcpListener::bind(addr_b).await?;
        let _stop_b = instance(b, "instance-b").await;
        tokio::time::sleep(interval * 4).await;
        let to_b = reached(&channel, "instance-b", 40).await;
        assert!(to_b >= 5, "{to_b} of 40 calls reached b after it returned");
        Ok(())
    }
}
