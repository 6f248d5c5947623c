"""MQTT5 client construction: one awscrt code path for AWS IoT Core, a TLS broker and a plain local mosquitto.

Shared by the subscriber, the edge simulator and the benchmark's load processes, so tests and the demo
exercise the same reconnect and backoff settings as production. awscrt is this module's reason to exist
(~70 ms to import); commands import it lazily so `twin --help` does not pay for it. boto3 stays lazy below:
only the "iot" path needs it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypedDict

from awscrt import auth, io, mqtt5
from awsiot import mqtt5_client_builder

from twin.core.aws import missing_profile_hint, region_or_env
from twin.transport.broker import NO_CREDENTIALS_HINT, BrokerConfig, BrokerConfigError


def resolve_iot_endpoint(config: BrokerConfig) -> str:
    """The account's IoT data endpoint: from the config, else iot:DescribeEndpoint (iot:Data-ATS)."""
    if config.endpoint:
        return config.endpoint
    import boto3  # noqa: PLC0415 - slow to import; only the "iot" path needs it
    from botocore.exceptions import NoCredentialsError, ProfileNotFound  # noqa: PLC0415 - with boto3

    try:
        # No region set: AWS_REGION, else boto3's own chain (AWS_DEFAULT_REGION, the profile's config).
        client = boto3.client("iot", region_name=region_or_env(config.region))
        response = client.describe_endpoint(endpointType="iot:Data-ATS")
    except NoCredentialsError as exc:
        raise BrokerConfigError(f"could not look up the IoT Core endpoint: {NO_CREDENTIALS_HINT}") from exc
    except ProfileNotFound as exc:
        # Not the endpoint fix below: no endpoint helps while the profile itself is missing.
        hint = missing_profile_hint(exc)
        raise BrokerConfigError(f"could not look up the IoT Core endpoint: {hint}") from exc
    except Exception as exc:
        raise BrokerConfigError(
            f"could not look up the IoT Core endpoint ({exc}); set [broker] endpoint (twin edge-sim: "
            "--endpoint) to the account's xxxx-ats.iot.<region>.amazonaws.com, or give the instance role "
            "iot:DescribeEndpoint"
        ) from exc
    return str(response["endpointAddress"])


def _region(config: BrokerConfig) -> str:
    region = region_or_env(config.region)
    if region:
        return region
    import boto3  # noqa: PLC0415 - see resolve_iot_endpoint
    from botocore.exceptions import ProfileNotFound  # noqa: PLC0415 - with boto3

    try:
        region = boto3.session.Session().region_name
    except ProfileNotFound as exc:
        raise BrokerConfigError(missing_profile_hint(exc)) from exc
    if not region:
        raise BrokerConfigError(
            "no AWS region for IoT Core: give --region (in an agent config, [broker] region), or set "
            "AWS_REGION or a region in the AWS config"
        )
    return str(region)


# awscrt calls each with its own event's data.
OnPublishReceived = Callable[[mqtt5.PublishReceivedData], None]
OnAttemptingConnect = Callable[[mqtt5.LifecycleAttemptingConnectData], None]
OnConnectionSuccess = Callable[[mqtt5.LifecycleConnectSuccessData], None]
OnConnectionFailure = Callable[[mqtt5.LifecycleConnectFailureData], None]
OnDisconnection = Callable[[mqtt5.LifecycleDisconnectData], None]
OnStopped = Callable[[mqtt5.LifecycleStoppedData], None]


class _CommonSettings(TypedDict):
    """The settings every variant shares, named as the SDK's builders take them as keyword arguments."""

    client_id: str
    session_behavior: mqtt5.ClientSessionBehaviorType
    retry_jitter_mode: mqtt5.ExponentialBackoffJitterMode
    min_reconnect_delay_ms: int
    max_reconnect_delay_ms: int
    keep_alive_interval_sec: int
    on_publish_received: OnPublishReceived | None
    on_lifecycle_attempting_connect: OnAttemptingConnect | None
    on_lifecycle_connection_success: OnConnectionSuccess | None
    on_lifecycle_connection_failure: OnConnectionFailure | None
    on_lifecycle_disconnection: OnDisconnection | None
    on_lifecycle_stopped: OnStopped | None


def build_mqtt5_client(
    config: BrokerConfig,
    client_id: str,
    *,
    on_publish_received: OnPublishReceived | None = None,
    on_attempting_connect: OnAttemptingConnect | None = None,
    on_connection_success: OnConnectionSuccess | None = None,
    on_connection_failure: OnConnectionFailure | None = None,
    on_disconnection: OnDisconnection | None = None,
    on_stopped: OnStopped | None = None,
) -> mqtt5.Client:
    """An unstarted awscrt MQTT5 client for `config`; shared by the subscriber and the edge simulator.

    Every variant uses a clean session, exponential backoff with FULL jitter and the configured delays, so a
    fleet of agents that lose IoT Core at once does not reconnect in lock step.
    """
    common: _CommonSettings = {
        "client_id": client_id,
        # Clean session: after every reconnect the broker has no subscriptions, and the connection-success
        # callback subscribes again. A persistent session would replay stale QoS1 traffic the twin does not
        # want (it only cares for the newest pose) and IoT Core expires it after an hour anyway.
        "session_behavior": mqtt5.ClientSessionBehaviorType.CLEAN,
        "retry_jitter_mode": mqtt5.ExponentialBackoffJitterMode.FULL,
        "min_reconnect_delay_ms": config.min_reconnect_delay_ms,
        "max_reconnect_delay_ms": config.max_reconnect_delay_ms,
        "keep_alive_interval_sec": config.keep_alive_s,
        "on_publish_received": on_publish_received,
        "on_lifecycle_attempting_connect": on_attempting_connect,
        "on_lifecycle_connection_success": on_connection_success,
        "on_lifecycle_connection_failure": on_connection_failure,
        "on_lifecycle_disconnection": on_disconnection,
        "on_lifecycle_stopped": on_stopped,
    }

    if config.kind == "iot":
        return _iot_client(config, common)
    if config.kind == "mqtts":
        return _tls_client(config, common)
    return _plain_client(config, common)


def _iot_client(config: BrokerConfig, common: _CommonSettings) -> mqtt5.Client:
    # SigV4 over WebSocket. The builder's handshake transform signs every connection attempt with fresh
    # credentials from the default chain (instance role via IMDS on EC2), so both rotated role credentials
    # and IoT Core's hard 24 h WebSocket lifetime are handled the same way: IoT Core closes the socket, the
    # client reports a disconnect, auto-reconnects with a newly signed handshake, and the connection-success
    # callback re-subscribes. Nothing here needs a timer for the 24 h cut.
    return mqtt5_client_builder.websockets_with_default_aws_signing(
        region=_region(config),
        credentials_provider=auth.AwsCredentialsProvider.new_default_chain(),
        endpoint=resolve_iot_endpoint(config),
        **common,
    )


def _tls_client(config: BrokerConfig, common: _CommonSettings) -> mqtt5.Client:
    # The SDK's plain-TLS builder; a private CA replaces the system trust store when given. Extended
    # validation is IoT-specific (8 filters per SUBSCRIBE, 100 publishes/s throttle), so it is off here.
    return mqtt5_client_builder.new_default_builder(
        endpoint=config.host,
        port=config.port,
        ca_filepath=config.ca_file or None,
        enable_metrics_collection=False,
        extended_validation_and_flow_control_options=(mqtt5.ExtendedValidationAndFlowControlOptions.NONE),
        **common,
    )


def _plain_client(config: BrokerConfig, common: _CommonSettings) -> mqtt5.Client:
    # Plain TCP: every SDK builder installs TLS, so build the options directly (docs/aws-facts.md).
    options = mqtt5.ClientOptions(
        host_name=config.host,
        port=config.port,
        tls_ctx=None,
        connect_options=mqtt5.ConnectPacket(
            client_id=common["client_id"], keep_alive_interval_sec=config.keep_alive_s
        ),
        session_behavior=common["session_behavior"],
        retry_jitter_mode=common["retry_jitter_mode"],
        min_reconnect_delay_ms=config.min_reconnect_delay_ms,
        max_reconnect_delay_ms=config.max_reconnect_delay_ms,
        socket_options=io.SocketOptions(),
        on_publish_callback_fn=common["on_publish_received"],
        on_lifecycle_event_attempting_connect_fn=common["on_lifecycle_attempting_connect"],
        on_lifecycle_event_connection_success_fn=common["on_lifecycle_connection_success"],
        on_lifecycle_event_connection_failure_fn=common["on_lifecycle_connection_failure"],
        on_lifecycle_event_disconnection_fn=common["on_lifecycle_disconnection"],
        on_lifecycle_event_stopped_fn=common["on_lifecycle_stopped"],
        disable_metrics=True,
    )
    return mqtt5.Client(options)
