#!/bin/bash
# EC2 UserData for the so101-twin host (rendered by stacks/twin_host.py, which fills the placeholders at synth).
# Kept tiny on purpose (16 KB limit): fetch the two S3 assets, then hand over to userdata/bootstrap.sh.
# No secret appears here: UserData is readable through IMDS and DescribeInstanceAttribute.
set -euo pipefail
exec > >(tee -a /var/log/so101-twin-bootstrap.log | logger -t so101-twin-bootstrap) 2>&1
export SO101_TWIN_LOGGING=1  # bootstrap.sh inherits this stream instead of adding a second tee
echo "so101-twin user-data: start $(date -Is)"

install -d -m 0755 /etc/so101-twin /opt/so101-twin
cat > /etc/so101-twin/settings.env <<'SETTINGS'
AWS_REGION=@@REGION@@
DCV_SECRET_ARN=@@SECRET_ARN@@
@@SETTINGS_ENV@@
SETTINGS

# The AWS CLI ships with the DLAMI; other Ubuntu AMIs get it from the snap store.
command -v aws >/dev/null 2>&1 || snap install aws-cli --classic

# The subnet assigns no public IP: the host is offline until CloudFormation associates the Elastic IP,
# so retry for a while instead of failing the whole boot.
fetch() {
  local attempt
  for attempt in $(seq 1 60); do
    if aws s3 cp --only-show-errors --region "@@REGION@@" "$1" "$2"; then return 0; fi
    echo "fetch $1: attempt $attempt failed, retrying in 10 s"
    sleep 10
  done
  return 1
}
fetch "@@AGENT_URL@@" /opt/so101-twin/agent-src.zip
fetch "@@SCRIPTS_URL@@" /opt/so101-twin/userdata.zip
rm -rf /opt/so101-twin/agent-src /opt/so101-twin/userdata
python3 -m zipfile -e /opt/so101-twin/agent-src.zip /opt/so101-twin/agent-src
python3 -m zipfile -e /opt/so101-twin/userdata.zip /opt/so101-twin/userdata
bash /opt/so101-twin/userdata/bootstrap.sh /etc/so101-twin/settings.env
