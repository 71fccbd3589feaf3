#!/usr/bin/env bash
# A throw-away certificate authority for tests and trials of mutual TLS:
#   scripts/make-test-ca.sh DIR [NAME ...]
# writes DIR/ca.pem (+ ca.key), DIR/server.pem/.key (for localhost and 127.0.0.1), and for
# each NAME (default: every user of the bundled mission) DIR/NAME.pem/.key with common name
# NAME, which the router's access control matches. Never use these keys in the field.
set -euo pipefail
dir=${1:?usage: make-test-ca.sh DIR [NAME ...]}
shift
names=("$@")
if [ ${#names[@]} -eq 0 ]; then
  names=(av-1 av-2 boat-1 boat-2 boat-3 boat-4 boat-5 gcs-gateway observer)
fi
mkdir -p "$dir"
cd "$dir"
openssl req -x509 -newkey rsa:2048 -nodes -keyout ca.key -out ca.pem -days 30 -subj "/CN=hetfleet test CA" 2>/dev/null
sign() { # name, extension file
  openssl req -newkey rsa:2048 -nodes -keyout "$1.key" -out "$1.csr" -subj "/CN=$1" 2>/dev/null
  openssl x509 -req -in "$1.csr" -CA ca.pem -CAkey ca.key -CAcreateserial -out "$1.pem" -days 30 -extfile "$2" 2>/dev/null
  rm -f "$1.csr"
  chmod 600 "$1.key"
}
printf 'subjectAltName=DNS:localhost,IP:127.0.0.1\nextendedKeyUsage=serverAuth,clientAuth\n' > server.ext
sign server server.ext
for n in "${names[@]}"; do
  printf 'subjectAltName=DNS:%s\nextendedKeyUsage=clientAuth\n' "$n" > "$n.ext"
  sign "$n" "$n.ext"
  rm -f "$n.ext"
done
rm -f server.ext ca.srl
chmod 600 ca.key
echo "test CA in $dir: ca.pem, server.pem, ${names[*]/%/.pem}"
