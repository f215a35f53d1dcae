//! `cell status` and `cell layout`: what a running cell is, as its holons answer.

use anyhow::Result;

use crate::client_args::{close, ClientArgs, OBSERVER};

/// Prints the live holons, the fenced resources and order-nodes, and the order-nodes.
pub async fn status(client: &ClientArgs) -> Result<bool> {
    let keys = client.keys()?;
    let session = client.session(OBSERVER).await?;
    let rows = cell::client::status::collect(&session, &keys, client.timeout()).await?;
    let nodes = cell::client::status::order_nodes(&session, &keys, client.timeout()).await;
    let fences = cell::client::status::fences(&session, &keys, client.timeout()).await;
    let node_fences = cell::client::status::node_fences(&session, &keys, client.timeout()).await;
    print!("{}", cell::client::status::render(&client.cell, &rows));
    match fences {
        Ok(fences) => print!("{}", cell::client::status::render_fences(&fences)),
        Err(e) => println!("fenced resources: cannot ask ({e})"),
    }
    match node_fences {
        Ok(reports) => print!("{}", cell::client::status::render_node_fences(&reports)),
        Err(e) => println!("fenced order-nodes: cannot ask ({e})"),
    }
    match nodes {
        Ok(nodes) => print!("{}", cell::client::status::render_order_nodes(&nodes)),
        Err(e) => println!("order-nodes: cannot ask ({e})"),
    }
    close(session).await;
    Ok(true)
}

/// Prints the running cell's layout, as text or JSON.
pub async fn layout(json: bool, client: &ClientArgs) -> Result<bool> {
    let keys = client.keys()?;
    let session = client.session(OBSERVER).await?;
    let layout = cell::client::layout::live(&session, &keys, client.timeout()).await;
    close(session).await;
    let layout = layout?;
    if json {
        println!("{}", serde_json::to_string_pretty(&layout)?);
    } else {
        print!(
            "{}",
            cell::client::layout::render(&client.cell, &layout, &Default::default())
        );
    }
    Ok(true)
}
