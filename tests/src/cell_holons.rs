//! Starting and driving the holons of a test cell: order-nodes, products, resources,
//! work orders, jobs and PackML commands.

use std::path::Path;
use std::time::Duration;

use anyhow::{anyhow, bail, Context, Result};
use schemas::{HolonId, MessageType, Service};

use crate::*;

impl Cell {
    /// Starts the demo's order-node `orders1` (its log and stderr in `dir`) with extra
    /// flags, and waits until it serves.
    pub async fn start_order_node(&self, dir: &Path, extra: &[&str]) -> Result<Process> {
        let process = start_holon(
            dir,
            "order-node",
            &demo_config("orders1.toml"),
            "orders1",
            self,
            extra,
        )?;
        self.wait_token(&self.keys.host("order-node", "orders1"))
            .await?;
        Ok(process)
    }

    /// Waits until a liveliness token on `key` appears (e.g. an order-node's host token).
    pub async fn wait_token(&self, key: &str) -> Result<()> {
        let found = holon::presence::wait_token(&self.session, key, WAIT)
            .await
            .map_err(|e| anyhow!("{e}"))?;
        if !found {
            bail!("{key} did not appear within {WAIT:?}");
        }
        Ok(())
    }

    /// The state of one order, asked of its order-node (`None`: no node knows it).
    pub async fn order_state(&self, order: &str) -> Option<serde_json::Value> {
        let replies = self
            .session
            .get(format!("holarchy/{}/order/{order}/state", self.keys.cell()))
            .timeout(Duration::from_secs(2))
            .await
            .ok()?;
        let reply = replies.recv_async().await.ok()?;
        serde_json::from_slice(&reply.result().ok()?.payload().to_bytes()).ok()
    }

    /// Waits, at most 20 s, until an order-node holds `order` (its task runs, its inbox
    /// is open: `host/order-node/*/held`, as a resource asks).
    pub async fn wait_held(&self, order: &str) -> Result<()> {
        let deadline = tokio::time::Instant::now() + crate::WAIT;
        let question = serde_json::to_vec(&schemas::HeldRequest {
            orders: vec![order.to_string()],
        })?;
        loop {
            let replies = self
                .session
                .get(self.keys.node_held_all())
                .payload(question.clone())
                .consolidation(zenoh::query::ConsolidationMode::None)
                .timeout(Duration::from_secs(1))
                .await
                .map_err(|e| anyhow::anyhow!("{e}"))?;
            while let Ok(reply) = replies.recv_async().await {
                let Ok(sample) = reply.result() else { continue };
                let answer: schemas::HeldReply =
                    serde_json::from_slice(&sample.payload().to_bytes())?;
                if answer.held.iter().any(|o| o == order) {
                    return Ok(());
                }
            }
            if tokio::time::Instant::now() >= deadline {
                bail!("no order-node held {order} within {:?}", crate::WAIT);
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }

    /// Waits, at most 30 s, until `check` holds for the order's state as its order-node
    /// answers it (`None`: no node knows the order). The error says what it never did.
    pub async fn wait_order(
        &self,
        order: &str,
        what: &str,
        check: impl Fn(Option<&serde_json::Value>) -> bool,
    ) -> Result<()> {
        let deadline = tokio::time::Instant::now() + Duration::from_secs(30);
        loop {
            let state = self.order_state(order).await;
            if check(state.as_ref()) {
                return Ok(());
            }
            if tokio::time::Instant::now() >= deadline {
                bail!("{order} never {what}: {state:?}");
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }

    /// Starts the product `part` (one `pick_n_place` step, [`one_step_product`]) and the
    /// order-node `orders1` of `orders_config` with its journal in `data`, and waits
    /// until both are in the cell.
    pub async fn start_part_and_orders(
        &self,
        dir: &Path,
        orders_config: &Path,
        data: &Path,
    ) -> Result<(Process, Process)> {
        let product = start_holon(
            dir,
            "holon-node",
            &one_step_product(dir)?,
            "part",
            self,
            &[],
        )?;
        let data = data.to_str().context("a data directory that is UTF-8")?;
        let orders = start_holon(
            dir,
            "order-node",
            orders_config,
            "orders1",
            self,
            &["--data-dir", data],
        )?;
        self.wait_alive(&HolonId::new(schemas::HolonKind::Product, "part")?)
            .await?;
        self.wait_token(&self.keys.host("order-node", "orders1"))
            .await?;
        Ok((product, orders))
    }

    /// [`Self::start_part_and_orders`] with the demo's order-node allowing
    /// `max_attempts` failed attempts a step (`orders.max_attempts`), its journal in
    /// DIR/orders-data.
    pub async fn start_part_and_demo_orders(
        &self,
        dir: &Path,
        max_attempts: u32,
    ) -> Result<(Process, Process)> {
        let config = dir.join("orders1.toml");
        let text = std::fs::read_to_string(crate::demo_config("orders1.toml"))?;
        let text = text.replace(
            "max_attempts = 3",
            &format!("max_attempts = {max_attempts}"),
        );
        anyhow::ensure!(
            text.contains(&format!("max_attempts = {max_attempts}")),
            "the demo's orders1.toml sets no max_attempts"
        );
        std::fs::write(&config, text)?;
        self.start_part_and_orders(dir, &config, &dir.join("orders-data"))
            .await
    }

    /// Starts the resource holon of `config` (its name is the file's stem) on this
    /// cell, driving the controller at `controller`, and waits until it is alive and
    /// free (its controller ready).
    pub async fn start_free_resource(
        &self,
        dir: &Path,
        config: &Path,
        controller: &str,
        extra: &[&str],
    ) -> Result<Process> {
        let node = start_node(
            dir,
            config,
            self.keys.cell(),
            &self.endpoint,
            controller,
            extra,
        )?;
        let name = config
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default();
        self.wait_alive(&HolonId::resource(&name)?).await?;
        self.wait_state(&name, "free", |s| s["state"] == "free")
            .await?;
        Ok(node)
    }

    /// A resource named `name` with its simulator, both in `dir`: configure it, then
    /// [`ResourceBuilder::start`] it.
    pub fn resource<'a>(&'a self, dir: &Path, name: &str) -> ResourceBuilder<'a> {
        ResourceBuilder {
            cell: self,
            dir: dir.to_path_buf(),
            name: name.to_string(),
            sim_flags: Vec::new(),
            command_timeout_ms: 5000,
            reconnect_interval_ms: None,
            config_extra: String::new(),
            node_flags: Vec::new(),
            dialect: None,
        }
    }

    /// Books and starts one `pick_n_place` job on `resource` for `order` (both must be
    /// accepted), and returns the result `inbox` (the order's) then gets.
    pub async fn job(
        &self,
        resource: &str,
        inbox: &mut Inbox,
        order: &str,
        conversation: &str,
    ) -> Result<Service> {
        for kind in [MessageType::BookingReq, MessageType::Start] {
            let request = pick_n_place(&self.keys, kind, order, conversation);
            let answer = self.service(resource, &request).await?;
            if answer.result != Some(true) {
                bail!("{kind:?} for {conversation} on {resource} refused: {answer:?}");
            }
        }
        inbox.next().await
    }

    /// Sends the PackML `command` (a name, e.g. `hold`) to `resource` over zenoh and
    /// returns its answer; an error if it was refused.
    pub async fn packml(&self, resource: &str, command: &str) -> Result<schemas::PackmlReply> {
        let command: schemas::PackmlCommand = command.parse().map_err(|e: String| anyhow!(e))?;
        let request = schemas::PackmlRequest::command(command, "a test");
        let replies = self
            .session
            .get(self.keys.packml(resource))
            .payload(serde_json::to_vec(&request)?)
            .timeout(WAIT)
            .await
            .map_err(|e| anyhow!("{e}"))?;
        let reply = replies
            .recv_async()
            .await
            .map_err(|_| anyhow!("{resource} did not answer the PackML {command}"))?;
        let sample = reply.result().map_err(|e| {
            anyhow!(
                "{resource} rejected the PackML {command}: {}",
                e.payload().try_to_string().unwrap_or_default()
            )
        })?;
        let answer: schemas::PackmlReply = serde_json::from_slice(&sample.payload().to_bytes())?;
        if let Some(why) = &answer.detail {
            bail!("{resource} refused {command}: {why}");
        }
        Ok(answer)
    }

    /// Waits until `resource` is in the PackML state numbered `state`.
    pub async fn wait_packml(&self, resource: &str, state: i32) -> Result<serde_json::Value> {
        self.wait_state(resource, &format!("PackML state {state}"), |s| {
            s["packml"]["state_number"] == state
        })
        .await
    }

    /// Waits until `resource` takes work again: free, and in Execute (a holon that
    /// dropped its controller connection is free at once but Suspended, refusing
    /// bookings, until it has connected again).
    pub async fn wait_serving(&self, resource: &str) -> Result<()> {
        self.wait_free(resource).await?;
        self.wait_packml(resource, 6).await.map(|_| ())
    }

    /// Waits until `resource` is free again.
    pub async fn wait_free(&self, resource: &str) -> Result<()> {
        self.wait_state(resource, "free again", |s| s["state"] == "free")
            .await
            .map(|_| ())
    }

    /// Submits a work order on `orders/submit` and returns the new orders' names.
    pub async fn submit(&self, product: &str, count: u32) -> Result<Vec<String>> {
        self.submit_work(schemas::WorkOrder {
            product: product.into(),
            count,
            priority: 0,
            due: None,
            queue: false,
            submit_id: None,
        })
        .await
    }

    /// Submits `work` on `orders/submit` and returns the new orders' names.
    pub async fn submit_work(&self, work: schemas::WorkOrder) -> Result<Vec<String>> {
        submit_on(&self.session, &self.keys, &work).await
    }
}
