#!/usr/bin/env node
// Validate a .glb/.gltf with the Khronos glTF validator (npm package gltf-validator).
// Usage: node tools/js/validate_gltf.js FILE
// Prints the report's summary as one JSON object:
//   {"validatorVersion", "numErrors", "numWarnings", "numInfos", "numHints", "messages": [...]}
// Exit code: 0 when the file has no errors, 1 when it has, 2 when it cannot be validated.
'use strict';
const fs = require('fs');
const path = require('path');

let validator;
try {
  validator = require(path.join(__dirname, 'node_modules', 'gltf-validator'));
} catch (e) {
  validator = require('gltf-validator');  // a global install
}

const file = process.argv[2];
if (!file) {
  console.error('usage: node validate_gltf.js FILE');
  process.exit(2);
}
const data = new Uint8Array(fs.readFileSync(file));
validator.validateBytes(data, { uri: path.basename(file), maxIssues: 100 }).then((report) => {
  const issues = report.issues;
  console.log(JSON.stringify({
    validatorVersion: report.validatorVersion,
    numErrors: issues.numErrors, numWarnings: issues.numWarnings,
    numInfos: issues.numInfos, numHints: issues.numHints,
    messages: issues.messages,
    info: report.info,
  }));
  process.exit(issues.numErrors > 0 ? 1 : 0);
}, (err) => {
  console.error(String(err));
  process.exit(2);
});
