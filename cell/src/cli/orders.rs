//! `cell orders`, `cell submit`, `cell cancel` and `cell part`: a running cell's orders, listed,
//! ordered, cancelled, and told where a lost part is.

use anyhow::{anyhow, Result};

use crate::client_args::{close, parse_due_in, ClientArgs, OBSERVER, OPERATOR};

/// `cell orders`: which orders, and how much of each.
#[derive(Debug, clap::Args)]
pub struct OrdersArgs {
    /// Also list every ended attempt of each order below it: conversation id, step,
    /// how it ended (done, rejected, failed, lost, no_resource, cancelled) and why.
    #[arg(long)]
    pub detail: bool,
    /// Which orders: all, running, finished, done, scrapped, failed or cancelled.
    #[arg(long, value_name = "STATUS", default_value = "all", value_parser = schemas::OrderFilter::parse)]
    pub status: schemas::OrderFilter,
    /// How many finished orders of each order-node to show, newest first.
    #[arg(long, value_name = "N", default_value_t = 20, conflicts_with = "all")]
    pub finished: usize,
    /// Show every finished order (page by page), not only the newest --finished.
    #[arg(long)]
    pub all: bool,
    #[command(flatten)]
    pub client: ClientArgs,
}

/// `cell submit`: the work order.
#[derive(Debug, clap::Args)]
pub struct SubmitArgs {
    /// The product to make, e.g. breaker.
    pub product: String,
    /// How many.
    #[arg(long, default_value_t = 1)]
    pub count: u32,
    /// Priority, -1000 to 1000 (higher first, e.g. 100 for a rush order): each
    /// resource serves waiting bookings by it, and passes a waiting booking at
    /// most `agenda.max_overtakes` times.
    #[arg(long, default_value_t = 0, allow_hyphen_values = true)]
    pub priority: i32,
    /// When the orders are due, from now: a number with a unit, ms, s, m or h
    /// (e.g. 90s, 15m). Kept and shown with each order; a staff holon plans by it.
    #[arg(long, value_name = "DURATION", value_parser = parse_due_in)]
    pub due_in: Option<std::time::Duration>,
    /// Accept the work order even when no product holon of that name is alive: its
    /// orders wait for the plan (refused `unknown_product` otherwise).
    #[arg(long)]
    pub queue: bool,
    /// A name for this work order (1 to 64 of a-z, 0-9, '_' and '-', e.g. an MES's
    /// work-order number), so that submitting it again is safe: the order-node answers
    /// with the orders it made under this name and makes none (a name given to another
    /// product or count is refused).
    #[arg(long, value_name = "NAME")]
    pub submit_id: Option<String>,
    #[command(flatten)]
    pub client: ClientArgs,
}

/// Prints the cell's orders; true when every order-node answered.
pub async fn list(args: OrdersArgs) -> Result<bool> {
    let client = args.client;
    let keys = client.keys()?;
    let session = client.session(OBSERVER).await?;
    let options = cell::client::orders::OrdersOptions {
        filter: args.status,
        finished: (!args.all).then_some(args.finished),
        detail: args.detail,
    };
    let mut out = std::io::stdout().lock();
    let complete = cell::client::orders::print(
        &session,
        &keys,
        &client.cell,
        &options,
        client.timeout(),
        &mut out,
    )
    .await;
    drop(out);
    close(session).await;
    complete
}

/// Submits the work order and prints the new orders' ids.
pub async fn submit(args: SubmitArgs) -> Result<bool> {
    let client = args.client;
    let keys = client.keys()?;
    let work = schemas::WorkOrder {
        product: args.product,
        count: args.count,
        priority: args.priority,
        due: args
            .due_in
            .map(|d| schemas::unix_ms() + d.as_millis() as u64),
        queue: args.queue,
        submit_id: args.submit_id,
    };
    work.validate()?;
    let session = client.session(OPERATOR).await?;
    let by = client.who_asks();
    let ids = cell::client::submit::submit(&session, &keys, &work, &by, client.timeout()).await?;
    println!("{}", ids.join("\n"));
    close(session).await;
    Ok(true)
}

/// Cancels the order and prints the node's answer.
/// `cell part ORDER --at LOCATION`: says where the order's lost part is.
pub async fn part(order: &str, at: String, client: &ClientArgs) -> Result<bool> {
    let keys = client.keys()?;
    schemas::HolonId::order(order)?;
    let at = schemas::layout::LocationId::try_from(at).map_err(|e| anyhow!("--at: {e}"))?;
    let session = client.session(OPERATOR).await?;
    let by = client.who_asks();
    let told =
        cell::client::part_word::tell(&session, &keys, order, &at, &by, client.timeout()).await;
    close(session).await;
    let reply = told?;
    println!("{}: {}", reply.order, reply.detail);
    Ok(true)
}

/// `cell carrier RESOURCE CARRIER --out|--back`: a conveyor's carrier taken out of
/// service or put back.
pub async fn carrier(
    resource: &str,
    carrier: &str,
    in_service: bool,
    client: &ClientArgs,
) -> Result<bool> {
    let keys = client.keys()?;
    schemas::HolonId::resource(resource)?;
    let session = client.session(OPERATOR).await?;
    let by = client.who_asks();
    let told = cell::client::carrier_word::tell(
        &session,
        &keys,
        resource,
        carrier,
        in_service,
        &by,
        client.timeout(),
    )
    .await;
    close(session).await;
    let reply = told?;
    println!("{resource}: {}", reply.detail);
    Ok(true)
}

pub async fn cancel(order: &str, client: &ClientArgs) -> Result<bool> {
    let keys = client.keys()?;
    schemas::HolonId::order(order)?;
    let session = client.session(OPERATOR).await?;
    let by = client.who_asks();
    let reply = cell::client::status::cancel(&session, &keys, order, &by, client.timeout()).await;
    close(session).await;
    let reply = reply?;
    println!("{}: {}", reply.order, reply.detail);
    Ok(true)
}
