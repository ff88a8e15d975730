#!/bin/sh
# Exit 0 while the local modbus-gateway is the active one of its pair, else 1.
# GET /role answers 200 while active and 503 while standing by (docs/redundancy.md).
# Set MODBUS_GATEWAY_ROLE_URL if the HTTP endpoint is not on 127.0.0.1:9502, and
# MODBUS_GATEWAY_TOKEN if [metrics] status_token is set.
url="${MODBUS_GATEWAY_ROLE_URL:-http://127.0.0.1:9502/role}"
if [ -n "${MODBUS_GATEWAY_TOKEN:-}" ]; then
    curl -sf -o /dev/null --max-time 1 -H "Authorization: Bearer ${MODBUS_GATEWAY_TOKEN}" "$url" || exit 1
else
    curl -sf -o /dev/null --max-time 1 "$url" || exit 1
fi
